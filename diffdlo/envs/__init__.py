"""Gymnasium environments; importing this module (done by ``import diffdlo``) registers them.

- ``DiffDLO/ShapeControl-v0``: ``gymnasium.make`` -> ShapeControlEnv (one rope),
  ``gymnasium.make_vec`` -> ShapeControlVectorEnv (B ropes, one batched simulator call per step).
- ``DiffDLO/Routing-v0``: the same env laying the rope along a route among pegs (target "route", a random board per
  episode; reward "route_gain"); any other option as for ShapeControl (target="route:u_two_pegs", action_type=
  "node_pin", ...).
- ``DiffDLO/Cable3D-v0`` (cable3d.py): a real cable's 3-D chain held at both ends by two grippers, brought to a
  target shape (diffdlo/tasks/cable3d.py's rules); ``make_vec`` -> Cable3DVectorEnv.
- ``BatchedShapeControl`` (core.py): the torch-native batched core both are built on (tensors in, tensors out); its
  state is one ``EnvState`` (state.py), its options one ``EnvOptions`` (options.py). The task's rules are
  diffdlo/tasks/task.py's.
"""
from gymnasium.envs.registration import register, registry

from ..tasks.task import ACTION_TYPES, OBS_TYPES
from .core import BatchedShapeControl
from .options import DEFAULT_VIEW_SIZE, EnvOptions
from .shape_control import ShapeControlEnv
from .state import EnvState
from .vector import ShapeControlVectorEnv

ENV_ID = "DiffDLO/ShapeControl-v0"
ROUTING_ENV_ID = "DiffDLO/Routing-v0"
CABLE3D_ENV_ID = "DiffDLO/Cable3D-v0"
CABLE3D_MAX_EPISODE_STEPS = 20

# gymnasium's time limit of the registered spec: the default params' episode length (ShapeControlEnv's docstring
# says how it meets the env's own max_steps).
MAX_EPISODE_STEPS = 100

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="diffdlo.envs.shape_control:ShapeControlEnv",
             vector_entry_point="diffdlo.envs.vector:ShapeControlVectorEnv", max_episode_steps=MAX_EPISODE_STEPS)
if ROUTING_ENV_ID not in registry:
    register(id=ROUTING_ENV_ID, entry_point="diffdlo.envs.shape_control:ShapeControlEnv",
             vector_entry_point="diffdlo.envs.vector:ShapeControlVectorEnv", max_episode_steps=MAX_EPISODE_STEPS,
             kwargs={"target": "route", "reward": "route_gain"})

if CABLE3D_ENV_ID not in registry:
    register(id=CABLE3D_ENV_ID, entry_point="diffdlo.envs.cable3d:Cable3DEnv",
             vector_entry_point="diffdlo.envs.cable3d:Cable3DVectorEnv", max_episode_steps=CABLE3D_MAX_EPISODE_STEPS)

__all__ = ["ACTION_TYPES", "CABLE3D_ENV_ID", "DEFAULT_VIEW_SIZE", "ENV_ID", "MAX_EPISODE_STEPS", "OBS_TYPES", "ROUTING_ENV_ID",
           "BatchedShapeControl",
           "EnvOptions", "EnvState", "ShapeControlEnv", "ShapeControlVectorEnv"]
