"""Writes the custom targets of this folder (run from the repository root: python planners/targets/make_targets.py).

arc.npy: a circular arc turning 90 degrees in total (constant turning angle 5 degrees at each of the 18 interior
nodes). s_curve.yaml: an S-curve, link direction 45 deg * sin(2 pi k / 18), k = 0..18 (turns up to ~15 deg per
node). Both are polylines of the rope's link length (0.5 m / 19) with the centroid at the origin.
"""
import math
from pathlib import Path

import numpy as np
import torch
import yaml

import diffdlo
from diffdlo.shapes import polyline_from_angles

here = Path(__file__).parent
p = diffdlo.load_params("cable")
k = torch.arange(p.n_nodes - 1, dtype=torch.float64).unsqueeze(0)
arc = polyline_from_angles((k - (p.n_nodes - 2) / 2) * math.radians(90 / (p.n_nodes - 2)), p.rest_length)[0]
np.save(here / "arc.npy", arc.numpy())
s = polyline_from_angles(math.radians(45) * torch.sin(2 * math.pi * k / (p.n_nodes - 2)), p.rest_length)[0]
(here / "s_curve.yaml").write_text(
    "# S-curve target for the 20-node, 0.5 m rope (planners/targets/make_targets.py)\npoints:\n"
    + "".join(f"  - [{x:.6f}, {y:.6f}]\n" for x, y in s.tolist()))
for f in ("arc.npy", "s_curve.yaml"):
    diffdlo.target_shape(here / f, p)        # validates link lengths
    print("wrote", here / f)
