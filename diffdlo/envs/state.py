"""The state of a batched shape-control env: one object, read and written only through ``get_state``/``set_state``."""
from __future__ import annotations

import copy
import dataclasses
from typing import Any

import numpy as np
import torch
from gymnasium.utils import seeding

from ..tasks.task import CUSTOM


@dataclasses.dataclass
class EnvState:
    """Everything the B episodes of a ``BatchedShapeControl`` are: read with ``get_state()`` (a copy), written with
    ``set_state()``. Tensors are (B, ...) on the env's device.

    pos, target (B, N, 2) [m]; steps (B,) moves since the reset; info: the per-rope figures of the last reset or
    move (task.task_metrics plus node (-1 after a reset) and substeps); target_names: the name of each rope's
    target (a named target, "random_curve" or "custom"); target_spec: what the next reset draws targets from (a
    family name or a fixed (N, 2) target); rngs: each rope's generator (None until first seeded or reset; the
    whole list None in a copy read without them);
    needs_reset (B,): ropes whose episode ended, reset by their next step under autoreset "next_step";
    pegs (B, max_pegs, 3): a route's pegs (x, y, radius) [m], rows of zeros past each layout's; None off routes.
    """
    pos: torch.Tensor
    target: torch.Tensor
    steps: torch.Tensor
    info: dict[str, torch.Tensor]
    target_names: list[str]
    target_spec: Any
    rngs: list[np.random.Generator | None] | None
    needs_reset: torch.Tensor
    pegs: torch.Tensor | None = None

    def clone(self, generators: bool = True) -> "EnvState":
        """A copy; ``generators=False`` leaves the generators out (rngs None): the cheap copy a reader needs."""
        return EnvState(self.pos.clone(), self.target.clone(), self.steps.clone(),
                        {k: v.clone() for k, v in self.info.items()}, list(self.target_names),
                        self.target_spec.clone() if torch.is_tensor(self.target_spec) else self.target_spec,
                        copy.deepcopy(self.rngs) if generators else None, self.needs_reset.clone(),
                        None if self.pegs is None else self.pegs.clone())

    def to_dict(self) -> dict[str, Any]:
        """Plain CPU tensors, lists and generator states (for checkpoints)."""
        return {"pos": self.pos.cpu().clone(), "target": self.target.cpu().clone(), "steps": self.steps.cpu().clone(),
                "info": {k: v.cpu().clone() for k, v in self.info.items()}, "target_names": list(self.target_names),
                "target_spec": self.target_spec.cpu() if torch.is_tensor(self.target_spec) else self.target_spec,
                "rngs": [None if r is None else r.bit_generator.state for r in self.rngs],
                "needs_reset": self.needs_reset.cpu().clone(),
                "pegs": None if self.pegs is None else self.pegs.cpu().clone()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "EnvState":
        rngs = []
        for st in d["rngs"]:
            rng = None
            if st is not None:
                rng = seeding.np_random(0)[0]
                rng.bit_generator.state = st
            rngs.append(rng)
        b = len(d["pos"])
        return cls(d["pos"], d["target"], d["steps"], dict(d["info"]),
                   list(d.get("target_names", [CUSTOM] * b)), d["target_spec"], rngs,
                   d.get("needs_reset", torch.zeros(b, dtype=torch.bool)), d.get("pegs"))
