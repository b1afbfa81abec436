"""Writes the custom targets of this folder (run from the repository root: python planners/targets/make_targets.py).

arc.npy: a circular arc turning 90 degrees in total (constant turning angle 5 degrees at each of the 18 interior
nodes). s_curve.yaml: an S-curve, link direction 45 deg * sin(2 pi k / 18), k = 0..18 (turns up to ~15 deg per
node). Held-out shapes (not members of the random_curve family, whose nodes turn at most 12 deg):
hook.npy: straight for the first half (nodes 0..10 on a line), then a smooth 120-degree bend spread over the second
half: a constant 120 / 9 = 13.3 deg turn at each of the interior nodes 10..18. wave.yaml: two periods of a sine in
the link direction, 30 deg * sin(4 pi k / 18), k = 0..18 (turns up to ~20 deg per node).
All are polylines of the rope's link length (0.5 m / 19) with the centroid at the origin.
"""
import math
from pathlib import Path

import numpy as np
import torch
import yaml

import diffdlo
from diffdlo.planar.shapes import polyline_from_angles

here = Path(__file__).parent
p = diffdlo.load_params("cable")
k = torch.arange(p.n_nodes - 1, dtype=torch.float64).unsqueeze(0)
arc = polyline_from_angles((k - (p.n_nodes - 2) / 2) * math.radians(90 / (p.n_nodes - 2)), p.rest_length)[0]
np.save(here / "arc.npy", arc.numpy())
s = polyline_from_angles(math.radians(45) * torch.sin(2 * math.pi * k / (p.n_nodes - 2)), p.rest_length)[0]
(here / "s_curve.yaml").write_text(
    "# S-curve target for the 20-node, 0.5 m rope (planners/targets/make_targets.py)\npoints:\n"
    + "".join(f"  - [{x:.6f}, {y:.6f}]\n" for x, y in s.tolist()))

# hook: the turn at interior node i (between links i-1 and i) is 0 for i <= (N-2)/2 and 120 deg / (N-2)/2 after.
half = (p.n_nodes - 2) // 2
turn = torch.zeros(1, p.n_nodes - 2, dtype=torch.float64)
turn[:, half:] = math.radians(120.0) / (p.n_nodes - 2 - half)
hook = polyline_from_angles(torch.cat([turn.new_zeros(1, 1), turn.cumsum(dim=1)], dim=1), p.rest_length)[0]
np.save(here / "hook.npy", hook.numpy())
wave = polyline_from_angles(math.radians(30) * torch.sin(4 * math.pi * k / (p.n_nodes - 2)), p.rest_length)[0]
(here / "wave.yaml").write_text(
    "# Wave target (two sine periods in the link direction, 30 deg) for the 20-node, 0.5 m rope "
    "(planners/targets/make_targets.py)\npoints:\n"
    + "".join(f"  - [{x:.6f}, {y:.6f}]\n" for x, y in wave.tolist()))
for f in ("arc.npy", "s_curve.yaml", "hook.npy", "wave.yaml"):
    diffdlo.target_shape(here / f, p)        # validates link lengths
    print("wrote", here / f)
