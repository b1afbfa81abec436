"""The tasks on the planar cable: their rules, written once, for the envs, the planners and the learners.

- ``task``: targets, action decoding, rewards, success (``task_success``), episode end, observations.
- ``rewards``: the thesis's rewards and ours, the shape error and the success test of a shape.
- ``routing``: the wire-harness task: a route among pegs, its side test and cost, boards (``layouts/``).
- ``image``: the pictures the envs observe (a batched rasterizer); ``demo``: ``python -m diffdlo.tasks.demo``.
"""
from . import image, rewards, routing, task  # noqa: F401
