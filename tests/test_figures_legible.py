"""The report's figures can be read at the size they are written: every text and legend lies inside the picture
after drawing, no legend covers an axes' data area or another text, no figure title covers a panel, the line plots
are at least ~700 px wide; and the precision figure draws a learner's 2 mm point as the tolerance ladder measured it
where that exists, else as a lower bound (an open marker, "≥", no line falling into it).

Built from the committed records (docs/results/cells.jsonl, one task: random; the precision rows on both of theirs),
each figure drawn once, as benchmarks.compare.figures writes it (its own dpi)."""
from pathlib import Path

import pytest

matplotlib = pytest.importorskip("matplotlib")

from benchmarks import compare  # noqa: E402
from benchmarks.compare import figures, report  # noqa: E402
from benchmarks.compare.precision import precise_rows  # noqa: E402

ROOT = Path(__file__).parents[1]
TASK = "random"
MIN_WIDTH_PX = 700


def _tick_labels(axis):
    """The tick labels an axis draws (those of the ticks within its view), with text."""
    ticks = axis._update_ticks()              # the ticks drawn: a locator's values may reach beyond the view
    return [lab for t in ticks for lab in (t.label1, t.label2) if lab.get_visible() and lab.get_text()]


def _shown(artist) -> bool:
    return artist is not None and artist.get_visible() and (not hasattr(artist, "get_text") or artist.get_text())


def problems(fig) -> list[str]:
    """What makes ``fig`` hard to read once drawn: text or legends cut at the canvas' edge, a legend over an axes'
    data area or over a text, a figure title over a panel or its texts."""
    from matplotlib.text import Text

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    canvas = fig.bbox
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend() is not None)]
    texts: list[tuple[str, Text]] = [(f"figure text {t.get_text()!r}", t) for t in fig.texts if _shown(t)]
    for i, ax in enumerate(fig.axes):
        named = [("title", ax.title), ("x label", ax.xaxis.label), ("y label", ax.yaxis.label),
                 *((f"x tick {t.get_text()!r}", t) for t in _tick_labels(ax.xaxis)),
                 *((f"y tick {t.get_text()!r}", t) for t in _tick_labels(ax.yaxis)),
                 *((f"text {t.get_text()!r}", t) for t in ax.texts)]
        texts += [(f"axes {i} {name}", t) for name, t in named if _shown(t)]
    out = []

    def inside(box) -> bool:
        return (box.x0 >= canvas.x0 - 0.5 and box.y0 >= canvas.y0 - 0.5 and box.x1 <= canvas.x1 + 0.5
                and box.y1 <= canvas.y1 + 0.5)

    boxes = [(name, t.get_window_extent(renderer)) for name, t in texts]
    for name, box in boxes:
        if not inside(box):
            out.append(f"{name} is cut by the canvas' edge: {box.bounds} outside {canvas.bounds}")
    for k, legend in enumerate(legends):
        box = legend.get_window_extent(renderer)
        if not inside(box):
            out.append(f"legend {k} is cut by the canvas' edge: {box.bounds} outside {canvas.bounds}")
        for i, ax in enumerate(fig.axes):
            if box.overlaps(ax.bbox):
                out.append(f"legend {k} covers the data area of axes {i}")
        for name, tbox in boxes:
            if box.overlaps(tbox):
                out.append(f"legend {k} covers {name}")
    for t in fig.texts:                          # the suptitle and other figure-level texts
        if not _shown(t):
            continue
        box = t.get_window_extent(renderer)
        for i, ax in enumerate(fig.axes):
            if box.overlaps(ax.bbox):
                out.append(f"figure text {t.get_text()!r} covers axes {i}")
        for name, tbox in boxes:
            if name.startswith("axes") and box.overlaps(tbox):
                out.append(f"figure text {t.get_text()[:40]!r} covers {name}")
    return out


@pytest.fixture(scope="module")
def committed():
    """(grid, [(cell, record)] of the committed records on TASK and the precision rows, {TASK: cost rows})."""
    grid = compare.load_grid()
    records = compare.read_records(ROOT / "docs/results/cells.jsonl")
    loaded, _ = report._loaded_from_records(compare.build_cells(grid, "runs/compare"), records)
    done = [(c, r) for c, r in loaded if r is not None]
    precise = {(m, v) for m, v, _ in precise_rows(grid)}
    keep = [(c, r) for c, r in done if c["target"] == TASK or (c["method"], c["variant"]) in precise]
    regular = [(c, r) for c, r in keep if (c["method"], c["variant"]) not in precise]
    costs = {TASK: [report._row(grid, Path("runs/compare"), TASK, key, items)[2]
                    for key, items in report.task_groups(regular, TASK).items()]}
    return grid, keep, costs


EXPECTED = ["summary.png", "precision.png", f"success_vs_steps_{TASK}.png", f"planner_error_vs_evals_{TASK}.png",
            f"gallery_{TASK}.png", f"cost_{TASK}.png"]


@pytest.mark.parametrize("quick", [False, True], ids=["full", "quick"])
@pytest.mark.parametrize("name", EXPECTED)
def test_each_report_figure_is_legible(committed, name, quick):
    """Each figure as the report writes it; ``quick``: as a quick run's (the same data, its titles marked)."""
    grid, done, costs = committed
    if quick:
        grid, name = dict(grid, name="quick"), f"quick_{name}"
    drawn = {n: (d, dpi) for n, d, dpi in figures.figures_to_draw(grid, done) + figures.cost_figures_to_draw(grid,
                                                                                                            costs)}
    assert name in drawn, sorted(drawn)
    draw, dpi = drawn[name]
    plt = figures._pyplot()
    fig = draw(plt)
    fig.set_dpi(dpi)                                 # as _save writes it
    try:
        assert problems(fig) == []
        assert fig.get_figwidth() * dpi >= MIN_WIDTH_PX, f"{name}: {fig.get_figwidth() * dpi:.0f} px wide"
    finally:
        plt.close(fig)


def test_the_check_finds_a_legend_over_the_axis_labels_and_a_cut_title():
    """The check itself: the old summary's fault (a figure legend at the bottom over the x labels, running off the
    left edge) and a title wider than its picture are found."""
    plt = figures._pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(5, 3))
    for ax in axes:
        ax.plot([1, 2], [1, 2], label="a long label that is a whole sentence, as the old summary's were " * 2)
        ax.set_xlabel("simulator moves spent")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="lower center", fontsize=7)
    fig.suptitle("a title far wider than the picture it belongs to, cut at both of its edges " * 2)
    try:
        found = problems(fig)
    finally:
        plt.close(fig)
    assert any("legend 0 is cut" in p for p in found)
    assert any(p.startswith("legend 0 covers axes 0 x tick") for p in found)          # over the x tick labels
    assert any("figure text" in p and "cut" in p for p in found)


def test_the_precision_figure_draws_the_ladder_where_it_measured_and_a_bound_where_nothing_did(committed):
    """PPO + policy rollouts' 2 mm on random is a lower bound in the grid's episodes (0 %) that the tolerance ladder
    measured (100 %): drawn at 100 %, with a black edge; the PETS-style model's on random has no ladder (≥ 4 %):
    an open marker with "≥", and no line falls into it."""
    grid, done, _ = committed
    by_key = {figures._key(c): r for c, r in done}
    points = {(p["label"], p["task"]): p for p in figures.ladder_points(grid, by_key)}
    ppo = points[("PPO + policy rollouts", TASK)]
    assert ppo["exact"][-1] is False and ppo["success"][-1] == 0.0 and ppo["measured"][-1] == 1.0
    assert ppo["ladder"] == "docs/results/tolerance_ladder_ppo.json"
    pets = points[("PETS-style world model", TASK)]
    assert pets["exact"][-1] is False and pets["measured"][-1] is None and pets["ladder"] is None
    assert points[("PETS-style world model", "random_curve")]["measured"][-1] == 1.0
    assert all(p["measured"] == [None] * 4 for (label, _), p in points.items() if "CEM" in label)

    plt = figures._pyplot()
    fig = figures._precision(plt, list(points.values()), "")
    try:
        ax = fig.axes[0]                                         # random
        colour = {p["label"]: f"C{i}" for i, p in enumerate(dict((p["label"], p) for p in points.values())
                                                               .values())}
        lines = [ln for ln in ax.lines if ln.get_color() == colour["PETS-style world model"]]
        ys = [y for ln in lines if len(ln.get_ydata()) > 1 for y in ln.get_ydata()]
        assert ys and min(ys) == 100.0                           # no segment reaches down to the bound
        bound = [ln for ln in lines if len(ln.get_ydata()) == 1 and ln.get_ydata()[0] == pytest.approx(4.0)]
        assert len(bound) == 1 and bound[0].get_markerfacecolor() == "none"
        assert [t.get_text() for t in ax.texts] == ["≥ 4 %"]
        ppo_lines = [ln for ln in ax.lines if ln.get_color() == colour["PPO + policy rollouts"]]
        at_2mm = [ln for ln in ppo_lines if len(ln.get_ydata()) == 1 and ln.get_xdata()[0] < 3]
        assert [ln.get_ydata()[0] for ln in at_2mm] == [100.0] and at_2mm[0].get_markeredgecolor() == "k"
        legend = [t.get_text() for t in fig.legends[0].get_texts()]
        assert any("tolerance ladder" in t for t in legend) and any(t.startswith("≥") for t in legend)
    finally:
        plt.close(fig)
