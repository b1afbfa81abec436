"""Pictures for people: ropes against their target (PNG) and a move or an episode as a GIF. Needs the [plot] extra
(matplotlib).

Every picture tells its lines apart the same way: the rope blue with its node 0 a red square, the target a grey
dashed line with its node 0 a grey circle (drawn at the rope's centroid by default: the shape error is
translation-free), the grasped node an orange star; one legend above the panels says so.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

MAX_COLS = 4          # panels per row, at most
MIN_PANEL_IN = 3.0    # a panel's side [inch], at least: smaller ones are unreadable
ROPE, TARGET, NODE0, GRASPED = "tab:blue", "tab:gray", "tab:red", "tab:orange"
PEG = "0.45"                  # a route's pegs: dark grey discs


def _pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ImportError("rendering pictures needs matplotlib: pip install 'diffdlo[plot]'") from exc
    return plt


def _np(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if torch.is_tensor(x) else np.asarray(x, dtype=np.float64)


def _shown_target(rope: np.ndarray, target: np.ndarray, align_target: bool) -> np.ndarray:
    return target - target.mean(0) + rope.mean(0) if align_target else target


def _draw(ax, rope: np.ndarray, target: np.ndarray | None, align_target: bool, color: str = ROPE,
          grasped: int | None = None, pegs: np.ndarray | None = None) -> None:
    """One rope (N, 2) against its target; ``grasped``: the node the last move held (None or < 0: none); ``pegs``
    (K, 3): a route's pegs, drawn to scale (rows of radius 0 are none)."""
    import matplotlib.patches as mpatches
    for x, y, r in ([] if pegs is None else pegs):
        if r > 0:
            ax.add_patch(mpatches.Circle((x, y), r, color=PEG, zorder=0))
    if target is not None:
        t = _shown_target(rope, target, align_target)
        ax.plot(t[:, 0], t[:, 1], "--", color=TARGET, lw=2)
        ax.plot(*t[0], "o", color=TARGET, ms=6, mfc="white", mew=2)
    ax.plot(rope[:, 0], rope[:, 1], "-o", color=color, ms=3, lw=2)
    ax.plot(*rope[0], "s", color=NODE0, ms=7)
    if grasped is not None and 0 <= int(grasped) < len(rope):
        ax.plot(*rope[int(grasped)], "*", color=GRASPED, ms=14, mec="black", mew=0.5)


def _square_view(ax, points: np.ndarray, margin: float = 0.15) -> None:
    """Limits of one square box around ``points`` (M, 2): every panel is filled alike, whatever its shape."""
    lo, hi = points.min(0), points.max(0)
    half = 0.5 * float((hi - lo).max()) * (1 + margin) + 0.005
    mid = 0.5 * (lo + hi)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)


def _style(ax, title: str | None) -> None:
    from matplotlib.ticker import MaxNLocator
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=8)
    ax.set_xlabel("x [m]", fontsize=8)
    ax.set_ylabel("y [m]", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)


def _legend(fig, has_target: bool, align_target: bool, has_grasped: bool, outside: bool = False,
            has_pegs: bool = False) -> float:
    """One legend above the panels naming the lines they show (``outside``: in a constrained layout's own row);
    returns the height it takes [inch]."""
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], color=ROPE, marker="o", ms=3, lw=2, label="rope"),
               Line2D([], [], color=NODE0, marker="s", ms=7, ls="", label="rope node 0")]
    if has_target:
        handles += [Line2D([], [], color=TARGET, ls="--", lw=2,
                           label="target (centred on the rope)" if align_target else "target"),
                    Line2D([], [], color=TARGET, marker="o", ms=6, mfc="white", mew=2, ls="", label="target node 0")]
    if has_grasped:
        handles.append(Line2D([], [], color=GRASPED, marker="*", ms=14, mec="black", mew=0.5, ls="",
                              label="grasped node"))
    if has_pegs:
        handles.append(Line2D([], [], color=PEG, marker="o", ms=9, ls="", label="peg"))
    ncol = 3 if fig.get_figwidth() >= 6 else 2           # a one-panel picture: two columns fit its width
    fig.legend(handles=handles, loc="outside upper center" if outside else "upper center", ncol=ncol,
               fontsize=9 if ncol == 3 else 8, frameon=False)
    return 0.25 * ((len(handles) + ncol - 1) // ncol) + 0.15


def _title(titles: Sequence[str] | None, errors: Sequence[float] | None, i: int) -> str | None:
    parts = [] if titles is None else [str(titles[i])]
    if errors is not None and errors[i] is not None:
        parts.append(f"shape error {float(errors[i]) * 100:.2f} cm")
    return "\n".join(p for p in parts if p) or None


def plot_ropes(ropes, target=None, path: str | Path | None = None, titles: Sequence[str] | None = None,
               align_target: bool = True, cols: int = 4, size: float = 3.5,
               errors: Sequence[float] | None = None, grasped: Sequence[int] | None = None, pegs=None):
    """Draw ropes (N, 2) or (B, N, 2) side by side, each against target (N, 2) or (B, N, 2).

    At most four panels a row (``cols`` fewer), each ``size`` >= 3 inches square. ``titles``: one per panel;
    ``errors``: each rope's shape error [m], added to its title; ``grasped``: the node each rope's last move held,
    starred. With align_target the target is drawn at the rope's centroid (the shape error is translation-free).
    ``pegs``: a route's pegs, (K, 3) for every panel or one (K, 3) per panel (draw a route with align_target=False:
    it lies where the pegs fix it). Saves a PNG if path is given; returns the matplotlib figure.
    """
    plt = _pyplot()
    ropes = _np(ropes)
    ropes = ropes[None] if ropes.ndim == 2 else ropes
    targets = None if target is None else _np(target)
    if targets is not None and targets.ndim == 2:
        targets = np.broadcast_to(targets, ropes.shape)
    n = ropes.shape[0]
    if pegs is not None:
        pegs = [_np(q) for q in pegs] if isinstance(pegs, (list, tuple)) else [_np(pegs)] * n
    cols = max(1, min(cols, MAX_COLS, n))
    rows = (n + cols - 1) // cols
    size = max(float(size), MIN_PANEL_IN)
    fig, axes = plt.subplots(rows, cols, figsize=(max(size * cols, 4.5), (size + 0.3) * rows + 0.6), squeeze=False,
                             layout="constrained")   # titles, labels and the legend never overlap
    fig.get_layout_engine().set(h_pad=0.1)
    for i, ax in enumerate(axes.flat):
        if i >= n:
            ax.axis("off")
            continue
        tgt = None if targets is None else targets[i]
        board = None if pegs is None else pegs[i]
        _draw(ax, ropes[i], tgt, align_target, grasped=None if grasped is None else grasped[i], pegs=board)
        shown = ropes[i] if tgt is None else np.concatenate([ropes[i], _shown_target(ropes[i], tgt, align_target)])
        if board is not None:
            shown = np.concatenate([shown, board[:, :2] - board[:, 2:], board[:, :2] + board[:, 2:]])
        _square_view(ax, shown)
        _style(ax, _title(titles, errors, i))
    has_grasped = grasped is not None and any(g is not None and int(g) >= 0 for g in grasped)
    _legend(fig, targets is not None, align_target, has_grasped, outside=True, has_pegs=pegs is not None)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=100)
        plt.close(fig)
    return fig


def save_gif(frames, path: str | Path, target=None, fps: int = 20, align_target: bool = True,
             title: str | Sequence[str] = "", grasped: Sequence[int] | None = None, size: float = 4.5,
             pegs=None) -> Path:
    """Write a GIF of rope frames (T, N, 2), e.g. MoveInfo.frames[:, b] or an episode's rope after every move, drawn
    against target (N, 2), or one target per frame (T, N, 2) (episodes one after another).

    ``title``: a prefix ("<title> frame i/T"), or one title per frame as given. ``grasped``: per frame, the node the
    move that led to it held (< 0: none), starred. ``size``: the picture's side [inch]. ``pegs`` (K, 3): a
    route's pegs, drawn in every frame.
    """
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    frames = _np(frames)
    tgt = None if target is None else _np(target)
    per_frame = tgt is not None and tgt.ndim == 3
    if per_frame and len(tgt) != len(frames):
        raise ValueError(f"one target per frame: got {len(tgt)} targets for {len(frames)} frames")
    if not isinstance(title, str) and len(title) != len(frames):
        raise ValueError(f"one title per frame: got {len(title)} titles for {len(frames)} frames")
    shown = None if tgt is None else np.stack([_shown_target(f, tgt[i] if per_frame else tgt, align_target)
                                               for i, f in enumerate(frames)])
    points = frames if shown is None else np.concatenate([frames, shown], axis=1)   # every frame's extent
    board = None if pegs is None else _np(pegs)
    points = points.reshape(-1, 2) if board is None else np.concatenate([points.reshape(-1, 2),
                                                                         board[:, :2] - board[:, 2:],
                                                                         board[:, :2] + board[:, 2:]])
    lo, hi = points.min(0), points.max(0)
    pad = 0.1 * float((hi - lo).max()) + 0.01
    fig, ax = plt.subplots(figsize=(size, size + 0.5))
    has_grasped = grasped is not None and any(int(g) >= 0 for g in grasped)
    top = _legend(fig, tgt is not None, align_target, has_grasped, has_pegs=board is not None)

    def draw(i: int):
        ax.clear()
        _draw(ax, frames[i], None if tgt is None else (tgt[i] if per_frame else tgt), align_target,
              grasped=None if grasped is None else grasped[i], pegs=board)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        _style(ax, f"{title} frame {i + 1}/{len(frames)}".strip() if isinstance(title, str) else title[i])

    draw(0)
    fig.tight_layout(rect=(0, 0, 1, 1 - top / fig.get_figheight()))   # once: every frame has the same layout
    anim = FuncAnimation(fig, draw, frames=len(frames))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
