"""Pictures for people: ropes against their target (PNG) and a move as a GIF. Needs the [plot] extra (matplotlib)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch


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


def _draw(ax, rope: np.ndarray, target: np.ndarray | None, align_target: bool, color: str = "tab:blue") -> None:
    if target is not None:
        t = target - target.mean(0) + rope.mean(0) if align_target else target
        ax.plot(t[:, 0], t[:, 1], "--", color="tab:gray", lw=2, label="target")
        ax.plot(*t[0], "o", color="tab:gray", ms=5)
    ax.plot(rope[:, 0], rope[:, 1], "-o", color=color, ms=3, lw=2, label="rope")
    ax.plot(*rope[0], "s", color="tab:red", ms=6, label="node 0")


def plot_ropes(ropes, target=None, path: str | Path | None = None, titles: Sequence[str] | None = None,
               align_target: bool = True, cols: int = 4, size: float = 3.0):
    """Draw ropes (N, 2) or (B, N, 2) side by side, each against target (N, 2) or (B, N, 2).

    With align_target the target is drawn at the rope's centroid (the shape error is translation-free).
    Saves a PNG if path is given; returns the matplotlib figure.
    """
    plt = _pyplot()
    ropes = _np(ropes)
    ropes = ropes[None] if ropes.ndim == 2 else ropes
    targets = None if target is None else _np(target)
    if targets is not None and targets.ndim == 2:
        targets = np.broadcast_to(targets, ropes.shape)
    n = ropes.shape[0]
    cols = min(cols, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(size * cols, size * rows), squeeze=False)
    for i, ax in enumerate(axes.flat):
        if i >= n:
            ax.axis("off")
            continue
        _draw(ax, ropes[i], None if targets is None else targets[i], align_target)
        ax.set_aspect("equal")
        ax.margins(0.15)
        ax.grid(alpha=0.3)
        if titles is not None:
            ax.set_title(titles[i], fontsize=9)
    axes.flat[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=100)
        plt.close(fig)
    return fig


def save_gif(frames, path: str | Path, target=None, fps: int = 20, align_target: bool = True,
             title: str = "") -> Path:
    """Write a GIF of rope frames (T, N, 2), e.g. MoveInfo.frames[:, b], drawn against target (N, 2)."""
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    frames = _np(frames)
    tgt = None if target is None else _np(target)
    lo = frames.reshape(-1, 2).min(0)
    hi = frames.reshape(-1, 2).max(0)
    if tgt is not None and align_target:
        # the aligned target follows the centroid; include its extent at every frame
        shifted = tgt[None] - tgt.mean(0) + frames.mean(1, keepdims=True)
        lo, hi = np.minimum(lo, shifted.reshape(-1, 2).min(0)), np.maximum(hi, shifted.reshape(-1, 2).max(0))
    pad = 0.1 * float((hi - lo).max()) + 0.01
    fig, ax = plt.subplots(figsize=(4, 4))

    def draw(i: int):
        ax.clear()
        _draw(ax, frames[i], tgt, align_target)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_title(f"{title} frame {i + 1}/{len(frames)}".strip(), fontsize=9)

    anim = FuncAnimation(fig, draw, frames=len(frames))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
