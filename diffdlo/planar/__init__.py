"""The planar cable model and its batched, differentiable simulator (the thesis's Chapter 2 model, after Lv et al.).

- ``params``: the cable's parameters (params/*.yaml), validated; ``physics``: the same as per-rope tensors.
- ``forces``: the chain's energy and forces (springs, bending); ``integrate``: the semi-implicit Euler step.
- ``control``: how a grasped node is dragged; ``contact``: pegs on the table (one board convention: radius 0 = no peg).
- ``shapes``: random and target rope shapes; ``rod``: the model as an elastic rod's numbers.
- ``simulator``: ``Simulator.move`` (grasp, drag, release, settle), the engines in ``backends`` (C++, Triton).
"""
from . import backends, contact, control, forces, integrate, params, physics, rod, shapes, simulator  # noqa: F401
