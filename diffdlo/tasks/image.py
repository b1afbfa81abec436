"""Batched torch rasterizer for rope images: anti-aliased distance-to-segment coverage on a pixel grid.

One call draws B polylines (B, N, 2) [m] into B images; everything stays on the input's device. The view is a
square window of side ``view_size`` metres centred at ``center`` (default the origin). Image convention: row 0 is
the top of the picture (largest y), column 0 the left (smallest x); pixel (r, c) has its centre at
x = x0 + (c + 0.5) * px, y = y1 - (r + 0.5) * px with px = view_size / size.
"""
from __future__ import annotations

import math

import torch

ROPE_COLOR = (200, 30, 30)        # red rope
TARGET_COLOR = (40, 90, 220)      # blue target
BACKGROUND = (255, 255, 255)      # white table
ROPE_END_COLOR = (30, 150, 40)    # green dot on the rope's node 0 (env option mark_end)
TARGET_END_COLOR = (250, 170, 0)  # amber dot on the target's node 0
PEG_COLOR = (110, 110, 110)       # grey pegs (a route's board)


def pixel_centres(size: int, view_size: float, center: tuple[float, float] = (0.0, 0.0),
                  device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(size, size, 2) world coordinates [m] of the pixel centres (row 0 at the top)."""
    px = view_size / size
    idx = torch.arange(size, device=device, dtype=dtype) + 0.5
    xs = center[0] - view_size / 2 + idx * px
    ys = center[1] + view_size / 2 - idx * px
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([grid_x, grid_y], dim=-1)


def world_to_pixel(points: torch.Tensor, size: int, view_size: float,
                   center: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """(..., 2) world [m] -> (..., 2) continuous (column, row) pixel coordinates."""
    scale = size / view_size
    col = (points[..., 0] - (center[0] - view_size / 2)) * scale
    row = ((center[1] + view_size / 2) - points[..., 1]) * scale
    return torch.stack([col, row], dim=-1)


def coverage(polylines: torch.Tensor, size: int, view_size: float, line_width: float | None = None,
             center: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """(B, N, 2) polylines [m] -> (B, size, size) coverage in [0, 1].

    Coverage of a pixel is clamp(0.5 + (w/2 - d) / px, 0, 1), d the distance from its centre to the nearest
    segment and w the line width [m] (default: 2 pixels, at least 1.5 % of the view): a one-pixel linear ramp
    that anti-aliases the stroke. Each segment only reaches the pixels within w/2 + px/2 of it, so every segment
    is drawn into a small window around its midpoint and the windows are merged with a max (coverage falls with
    distance, so the max over segments is the coverage of the nearest one). Cost O(B * (N - 1) * window^2)
    instead of O(B * size^2 * (N - 1)).
    """
    if polylines.ndim != 3 or polylines.shape[-1] != 2 or polylines.shape[1] < 2:
        raise ValueError(f"polylines must have shape (B, N>=2, 2), got {tuple(polylines.shape)}")
    px = view_size / size
    width = line_width if line_width is not None else max(2.0 * px, 0.015 * view_size)
    dtype = polylines.dtype if polylines.is_floating_point() else torch.float32
    pts = world_to_pixel(polylines.to(dtype), size, view_size, center)   # pixel (r, c) centred at (c + .5, r + .5)
    batch, device = pts.shape[0], pts.device
    a, b = pts[:, :-1], pts[:, 1:]                                      # (B, S, 2)
    ab = b - a
    reach = 0.5 * float(ab.detach().norm(dim=-1).amax()) + width / (2 * px) + 0.5
    if not math.isfinite(reach):
        raise ValueError("polylines contain NaN or inf")
    half = int(math.ceil(reach))
    k = 2 * half + 1
    corner = torch.floor((a + b) / 2).to(torch.int64) - half            # (B, S, 2) window corner (col, row)
    offsets = torch.arange(k, device=device)
    cols = corner[..., 0, None, None] + offsets.view(1, 1, 1, k)        # (B, S, 1, K)
    rows = corner[..., 1, None, None] + offsets.view(1, 1, k, 1)        # (B, S, K, 1)
    cx = cols.to(dtype) + 0.5 - a[..., 0, None, None]
    cy = rows.to(dtype) + 0.5 - a[..., 1, None, None]
    abx, aby = ab[..., 0, None, None], ab[..., 1, None, None]
    t = ((cx * abx + cy * aby) / (abx * abx + aby * aby).clamp_min(1e-12)).clamp(0.0, 1.0)
    dist = ((cx - t * abx) ** 2 + (cy - t * aby) ** 2).sqrt()          # (B, S, K, K) [pixels]
    cov = (0.5 + width / (2 * px) - dist).clamp(0.0, 1.0)
    inside = (cols >= 0) & (cols < size) & (rows >= 0) & (rows < size)
    index = torch.where(inside, rows * size + cols, torch.zeros_like(rows))
    cov = torch.where(inside, cov, torch.zeros_like(cov))
    out = torch.zeros(batch, size * size, device=device, dtype=dtype)
    out.scatter_reduce_(1, index.reshape(batch, -1), cov.reshape(batch, -1), reduce="amax", include_self=True)
    return out.view(batch, size, size)


def end_marker(polylines: torch.Tensor, size: int, view_size: float, diameter: float | None = None,
               center: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """(B, N, 2) polylines [m] -> (B, size, size) coverage of a dot on each polyline's FIRST point (node 0).

    Without it a rope and its reversal draw the same picture, though node i is compared with target node i: a
    straight rope lying on a straight target the wrong way round is 0.26 m off and looks solved. ``diameter``
    default: 2.5 pixels.
    """
    first = polylines[:, :1]
    return coverage(torch.cat([first, first], dim=1), size, view_size,
                    diameter if diameter is not None else 2.5 * view_size / size, center)


def discs(circles: torch.Tensor, size: int, view_size: float,
          center: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """(B, K, 3) circles (x, y, radius) [m] -> (B, size, size) anti-aliased coverage of their union (rows of radius
    0 draw nothing)."""
    grid = pixel_centres(size, view_size, center, circles.device, circles.dtype)            # (S, S, 2)
    px = view_size / size
    dist = (grid[None, None] - circles[:, :, None, None, :2]).norm(dim=-1)                  # (B, K, S, S)
    radius = circles[..., 2][:, :, None, None]
    cover = ((radius - dist) / px + 0.5).clamp(0.0, 1.0) * (radius > 0)
    return cover.amax(1) if circles.shape[1] else grid.new_zeros(circles.shape[0], size, size)


def compose(layers: list[tuple[torch.Tensor, tuple[int, int, int]]],
            background: tuple[int, int, int] = BACKGROUND) -> torch.Tensor:
    """Alpha-blend coverage layers (B, H, W) with their RGB colours over the background -> (B, H, W, 3) uint8."""
    first = layers[0][0]
    img = torch.tensor(background, dtype=torch.float32, device=first.device).expand(*first.shape, 3).clone()
    for cov, color in layers:
        col = torch.tensor(color, dtype=torch.float32, device=cov.device)
        alpha = cov.to(torch.float32).unsqueeze(-1)
        img = img * (1 - alpha) + col * alpha
    return img.round().clamp(0, 255).to(torch.uint8)


def render_ropes(ropes: torch.Tensor | None, targets: torch.Tensor | None = None, size: int = 64,
                 view_size: float = 1.0, line_width: float | None = None,
                 center: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """(B, N, 2) ropes and/or targets [m] -> (B, size, size, 3) uint8 RGB; the rope is drawn over the target.

    Either argument may be None (draw only the other). Targets may be (N, 2) (broadcast) or (B, N, 2).
    """
    if ropes is None and targets is None:
        raise ValueError("render_ropes needs ropes, targets or both")
    batch = ropes.shape[0] if ropes is not None else (targets.shape[0] if targets.ndim == 3 else 1)
    layers = []
    if targets is not None:
        if targets.ndim == 2:
            targets = targets.unsqueeze(0).expand(batch, *targets.shape)
        layers.append((coverage(targets, size, view_size, line_width, center), TARGET_COLOR))
    if ropes is not None:
        layers.append((coverage(ropes, size, view_size, line_width, center), ROPE_COLOR))
    return compose(layers)
