"""Gymnasium environments; importing this module (done by ``import diffdlo``) registers them.

- ``DiffDLO/ShapeControl-v0``: ``gymnasium.make`` -> ShapeControlEnv (one rope),
  ``gymnasium.make_vec`` -> ShapeControlVectorEnv (B ropes, one batched simulator call per step).
- ``BatchedShapeControl`` (core.py): the torch-native batched core both are built on (tensors in, tensors out); its
  state is one ``EnvState`` (state.py). The task's rules are diffdlo/task.py's.
"""
from gymnasium.envs.registration import register, registry

from .core import ACTION_TYPES, DEFAULT_VIEW_SIZE, OBS_TYPES, BatchedShapeControl
from .shape_control import ShapeControlEnv
from .state import EnvState
from .vector import ShapeControlVectorEnv

ENV_ID = "DiffDLO/ShapeControl-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="diffdlo.envs.shape_control:ShapeControlEnv",
             vector_entry_point="diffdlo.envs.vector:ShapeControlVectorEnv")

__all__ = ["ACTION_TYPES", "DEFAULT_VIEW_SIZE", "ENV_ID", "OBS_TYPES", "BatchedShapeControl", "EnvState",
           "ShapeControlEnv",
           "ShapeControlVectorEnv"]
