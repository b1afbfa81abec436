"""The package's layout as docs/ARCHITECTURE.md draws it: no import cycle anywhere in the project, counting the
imports hidden inside functions, and the layers one way: the planar simulator below the tasks, diffdlo below the
planners, the planners below the learners, nothing above the benchmarks."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("diffdlo", "planners", "agents", "benchmarks")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """The project modules ``name`` imports, at its top or inside functions (a package's import of its own
    submodule's names counts as importing that submodule)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):   # not a package above itself
                found.add(target)
    return found


def graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: imports(path, name, modules) for name, path in modules.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_no_module_imports_itself_round_a_circle():
    found = cycles(graph())
    assert not found, f"import cycles (counting imports inside functions): {found}"


def test_the_cycle_finder_finds_a_hidden_circle():
    edges = {"planners.common": {"planners.escape"}, "planners.escape": {"planners.greedy"},
             "planners.greedy": {"planners.common"}, "planners.cem": {"planners.common"}}
    assert cycles(edges) == [["planners.common", "planners.escape", "planners.greedy"]]


def test_the_layers_import_one_way():
    below = {"diffdlo.planar": ("diffdlo.tasks", "diffdlo.envs", "diffdlo.perception", "diffdlo.calibration",
                                "diffdlo.chain3d", "planners", "agents", "benchmarks"),
             "diffdlo.tasks": ("diffdlo.envs", "diffdlo.perception", "diffdlo.calibration", "planners", "agents",
                               "benchmarks"),
             "diffdlo": ("planners", "agents", "benchmarks"),
             "planners": ("agents", "benchmarks"),
             "agents": ("benchmarks",)}
    upward = []
    for name, targets in graph().items():
        for layer, above in below.items():
            if name == layer or name.startswith(layer + "."):
                upward += [f"{name} -> {t}" for t in targets
                           if any(t == a or t.startswith(a + ".") for a in above)]
                break
    assert not upward, upward
