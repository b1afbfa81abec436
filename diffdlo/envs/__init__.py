"""Gymnasium environments; importing this module (done by ``import diffdlo``) registers them.

- ``DiffDLO/ShapeControl-v0``: ``gymnasium.make`` -> ShapeControlEnv (one rope),
  ``gymnasium.make_vec`` -> ShapeControlVectorEnv (B ropes, one batched simulator call per step).
- ``BatchedShapeControl``: the torch-native batched core both are built on (tensors in, tensors out).
"""
from gymnasium.envs.registration import register, registry

from .shape_control import (ACTION_TYPES, DEFAULT_VIEW_SIZE, OBS_TYPES, BatchedShapeControl, ShapeControlEnv)
from .vector import ShapeControlVectorEnv

ENV_ID = "DiffDLO/ShapeControl-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="diffdlo.envs.shape_control:ShapeControlEnv",
             vector_entry_point="diffdlo.envs.vector:ShapeControlVectorEnv")

__all__ = ["ACTION_TYPES", "DEFAULT_VIEW_SIZE", "ENV_ID", "OBS_TYPES", "BatchedShapeControl", "ShapeControlEnv",
           "ShapeControlVectorEnv"]
