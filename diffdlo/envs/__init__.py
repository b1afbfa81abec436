"""Gymnasium environments; importing this module (done by ``import diffdlo``) registers them.

- ``DiffDLO/ShapeControl-v0``: ``gymnasium.make`` -> ShapeControlEnv (one rope),
  ``gymnasium.make_vec`` -> ShapeControlVectorEnv (B ropes, one batched simulator call per step).
- ``BatchedShapeControl`` (core.py): the torch-native batched core both are built on (tensors in, tensors out); its
  state is one ``EnvState`` (state.py), its options one ``EnvOptions`` (options.py). The task's rules are
  diffdlo/task.py's.
"""
from gymnasium.envs.registration import register, registry

from ..task import ACTION_TYPES, OBS_TYPES
from .core import BatchedShapeControl
from .options import DEFAULT_VIEW_SIZE, EnvOptions
from .shape_control import ShapeControlEnv
from .state import EnvState
from .vector import ShapeControlVectorEnv

ENV_ID = "DiffDLO/ShapeControl-v0"

# gymnasium's time limit of the registered spec: the default params' episode length (ShapeControlEnv's docstring
# says how it meets the env's own max_steps).
MAX_EPISODE_STEPS = 100

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="diffdlo.envs.shape_control:ShapeControlEnv",
             vector_entry_point="diffdlo.envs.vector:ShapeControlVectorEnv", max_episode_steps=MAX_EPISODE_STEPS)

__all__ = ["ACTION_TYPES", "DEFAULT_VIEW_SIZE", "ENV_ID", "MAX_EPISODE_STEPS", "OBS_TYPES", "BatchedShapeControl",
           "EnvOptions", "EnvState", "ShapeControlEnv", "ShapeControlVectorEnv"]
