"""Cable parameters: a frozen dataclass loaded and validated from ``params/*.yaml``."""
from __future__ import annotations

import dataclasses
import math
from importlib import resources
from pathlib import Path
from typing import Any

import yaml


def _find_params_dir() -> Path:
    """The folder the parameter files (``cable.yaml`` and the agents' presets) are read from.

    A built wheel ships the repository's ``params/`` inside the package as ``diffdlo/_params`` (setup.cfg maps it),
    so an installed package finds them wherever it lives. A source checkout (an editable install, or the repository
    on ``sys.path``) has no such folder and reads ``params/`` at the repository root, the files the README names.
    """
    packaged = resources.files("diffdlo") / "_params"
    if packaged.is_dir():
        return Path(packaged)
    return Path(__file__).resolve().parents[2] / "params"


PARAMS_DIR = _find_params_dir()

CONTROLLERS = ("kinematic", "pid")

# YAML section -> {yaml key: dataclass field}. Every key is required.
_LAYOUT = {
    "model": {
        "n_nodes": "n_nodes", "length": "length", "mass": "mass", "k_s": "k_s", "k_b": "k_b",
        "k_d": "k_d", "dt": "dt",
    },
    "controller": {
        "type": "controller", "max_speed": "max_speed", "max_disp": "max_disp", "max_steps": "max_drag_steps",
        "k_p": "k_p", "k_i": "k_i", "k_ff": "k_ff", "ff_len": "ff_len",
    },
    "settle": {
        "threshold": "settle_threshold", "check_every": "settle_check_every",
        "max_substeps": "settle_max_substeps",
    },
    "contact": {
        "rope_radius": "rope_radius", "stiffness": "contact_stiffness", "width": "contact_width",
    },
    "env": {
        "sigma": "sigma", "action_scale": "action_scale", "workspace": "workspace",
        "max_steps": "max_episode_steps", "success_tol": "success_tol", "success_bonus": "success_bonus",
    },
}

# Keys that older files carry but that never drove anything: a file that still has one is rejected with this
# reason, so its author learns the value was ignored (params/cable.yaml keeps the thesis's numbers in prose).
# Each was also a dataclass field of the same name.
_REMOVED = {
    ("model", "k_f"): "the thesis's Table 2.1 K_f has no term in the planar model (eq 2.1-2.3), so nothing read it",
    ("controller", "ff_dt"): "the PID's force profile is evaluated at every integrator substep dt, so nothing "
                             "read it",
}


class ParamsError(ValueError):
    """A cable parameter file or value is invalid; the message names the field and the value."""


@dataclasses.dataclass(frozen=True)
class CableParams:
    """All numbers of the cable model, its controller, the settle rule and the task. See params/cable.yaml."""

    # model (Table 2.1)
    n_nodes: int
    length: float
    mass: float
    k_s: float
    k_b: float
    k_d: float
    dt: float
    # controller (Chapter 2 §1)
    controller: str
    max_speed: float
    max_disp: float
    max_drag_steps: int
    k_p: float
    k_i: float
    k_ff: float
    ff_len: float
    # free evolution (Algorithms 1-3)
    settle_threshold: float
    settle_check_every: int
    settle_max_substeps: int
    # contact with pegs (diffdlo/planar/contact.py)
    rope_radius: float
    contact_stiffness: float
    contact_width: float
    # task (thesis Algorithms 1-2)
    sigma: float
    action_scale: float
    workspace: tuple[float, float]
    max_episode_steps: int
    success_tol: float
    success_bonus: float

    def __post_init__(self) -> None:
        validate(self)

    @property
    def rest_length(self) -> float:
        """Rest length of one link [m]."""
        return self.length / (self.n_nodes - 1)

    @property
    def node_mass(self) -> float:
        """Mass of one node [kg]: the total mass shared equally."""
        return self.mass / self.n_nodes

    def stability_margin(self, contact: bool = False) -> float:
        """dt^2 w_max^2 / limit of the semi-implicit Euler step with implicit damping; stable below 1.

        For a mode of angular frequency w the step is stable iff dt^2 w^2 < 2 (2 + dt k_d / m). w_max^2 is
        bounded by the stiffest axial mode 4 k_s / m plus the stiffest bending mode 16 k_b / (l0^2 m), and with
        ``contact`` (a move with pegs) plus 2 k_c / m: a node pressed into a peg by both of its links, each with
        its share <= 1 of k_c. ``validate`` checks the rope's own margin; a move with pegs checks the contact's.
        """
        m = self.node_mass
        w2 = (4.0 * self.k_s + 16.0 * self.k_b / self.rest_length ** 2
              + (2.0 * self.contact_stiffness if contact else 0.0)) / m
        return self.dt ** 2 * w2 / (2.0 * (2.0 + self.dt * self.k_d / m))


def _check_number(name: str, value: Any, *, integer: bool = False) -> None:
    kinds = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kinds):
        want = "an integer" if integer else "a number"
        raise ParamsError(f"cable parameter {name!r} must be {want}, got {value!r} ({type(value).__name__})")
    if not math.isfinite(value):
        raise ParamsError(f"cable parameter {name!r} must be finite, got {value!r}")


# Allowed range of every numeric field: field -> (lower bound, whether the bound itself is allowed, a reason where
# the bound is not obvious). An error names the field, the value and this range.
_RANGES: dict[str, tuple[float, bool, str]] = {
    "n_nodes": (3, True, "bending needs an interior node"),
    "length": (0, False, ""),
    "mass": (0, False, ""),
    "k_s": (0, False, "the links' axial springs hold the rope together"),
    "k_b": (0, True, "0 is a chain that does not resist bending"),
    "k_d": (0, True, "0 is undamped"),
    "dt": (0, False, ""),
    "max_speed": (0, False, ""),
    "max_disp": (0, False, ""),
    "max_drag_steps": (1, True, ""),
    "k_p": (0, True, ""),
    "k_i": (0, True, ""),
    "k_ff": (0, True, ""),
    "ff_len": (0, True, ""),
    "settle_threshold": (0, True, ""),
    "settle_check_every": (1, True, ""),
    "settle_max_substeps": (0, True, ""),
    "rope_radius": (0, False, ""),
    "contact_stiffness": (0, False, "the pegs' penalty must push"),
    "contact_width": (0, False, ""),
    "sigma": (0, True, ""),
    "action_scale": (0, False, ""),
    "max_episode_steps": (1, True, ""),
    "success_tol": (0, False, ""),
    "success_bonus": (0, True, ""),
}


def _check_range(name: str, value: float) -> None:
    bound, inclusive, why = _RANGES[name]
    if value >= bound if inclusive else value > bound:
        return
    allowed = f"{'>=' if inclusive else '>'} {bound}" + (f" ({why})" if why else "")
    raise ParamsError(f"cable parameter {name!r} must be {allowed}, got {value!r}")


def validate(p: CableParams) -> None:
    """Raise ParamsError naming the first bad field, its value and the allowed range."""
    ints = {"n_nodes", "max_drag_steps", "settle_check_every", "settle_max_substeps", "max_episode_steps"}
    for f in dataclasses.fields(p):
        value = getattr(p, f.name)
        if f.name == "controller":
            if value not in CONTROLLERS:
                raise ParamsError(f"cable parameter 'controller' must be one of {CONTROLLERS}, got {value!r}")
        elif f.name == "workspace":
            if not isinstance(value, (tuple, list)) or len(value) != 2:
                raise ParamsError(f"cable parameter 'workspace' must be [width, height], got {value!r}")
            for v in value:
                _check_number("workspace", v)
                if v <= 0:
                    raise ParamsError(f"cable parameter 'workspace' must be > 0 in both axes, got {value!r}")
        else:
            _check_number(f.name, value, integer=f.name in ints)
            _check_range(f.name, value)
    margin = p.stability_margin()
    if margin >= 1.0:
        raise ParamsError(
            f"cable parameter 'dt' = {p.dt} makes the integrator unstable with k_s={p.k_s}, k_b={p.k_b}, "
            f"k_d={p.k_d}, node mass={p.node_mass:.4g}: dt^2*w_max^2 is {margin:.3g}x the stability limit "
            f"(must be < 1); use a smaller dt")


def check_contact_stability(p: CableParams) -> None:
    """ParamsError naming the contact stiffness where pegs would make the integrator unstable (see
    CableParams.stability_margin); called by every move and free evolution with pegs."""
    margin = p.stability_margin(contact=True)
    if margin >= 1.0:
        raise ParamsError(
            f"cable parameter 'contact_stiffness' = {p.contact_stiffness} N/m makes the integrator unstable with "
            f"pegs (dt={p.dt}, k_s={p.k_s}, k_b={p.k_b}, k_d={p.k_d}, node mass={p.node_mass:.4g}): "
            f"dt^2*w_max^2 is {margin:.3g}x the stability limit (must be < 1); use a softer contact or a smaller dt")


def load_params(name_or_path: str | Path = "cable", **overrides: Any) -> CableParams:
    """Load cable parameters by name (``params/<name>.yaml``) or from a YAML path, then apply overrides.

    Raises ParamsError naming the missing or bad field.
    """
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = PARAMS_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        raise ParamsError(f"no cable parameter file {str(name_or_path)!r} (looked for {path})")
    with open(path) as fh:
        try:
            raw = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise ParamsError(f"{path} is not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise ParamsError(f"{path} must hold a mapping with sections {list(_LAYOUT)}, got {type(raw).__name__}")
    values: dict[str, Any] = {}
    for section, keys in _LAYOUT.items():
        block = raw.get(section)
        if not isinstance(block, dict):
            raise ParamsError(f"{path}: missing section {section!r}")
        for key, field in keys.items():
            if key not in block:
                raise ParamsError(f"{path}: missing field '{section}.{key}'")
            values[field] = block[key]
        unknown = set(block) - set(keys)
        for key in sorted(unknown):
            if (section, key) in _REMOVED:
                raise ParamsError(f"{path}: field '{section}.{key}' was removed because it did nothing "
                                  f"({_REMOVED[section, key]}); delete it from the file")
        if unknown:
            raise ParamsError(f"{path}: unknown field(s) in section {section!r}: {sorted(unknown)}")
    unknown_sections = set(raw) - set(_LAYOUT)
    if unknown_sections:
        raise ParamsError(f"{path}: unknown section(s) {sorted(unknown_sections)}")
    bad = set(overrides) - {f.name for f in dataclasses.fields(CableParams)}
    for (_, name), reason in _REMOVED.items():
        if name in bad:
            raise ParamsError(f"cable parameter {name!r} was removed because it did nothing ({reason})")
    if bad:
        raise ParamsError(f"unknown cable parameter override(s) {sorted(bad)}")
    values.update(overrides)
    if isinstance(values["workspace"], list):
        values["workspace"] = tuple(values["workspace"])
    return CableParams(**values)
