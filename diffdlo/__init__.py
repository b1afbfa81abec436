"""diffdlo: a batched, differentiable simulator of a planar deformable linear object (cable) and its tasks."""
from .planar.forces import energy, internal_forces, turning_angles
from .planar.backends.kernel import KernelUnavailableWarning
from .planar.params import CableParams, ParamsError, load_params
from .planar.physics import Physics
from .tasks.rewards import (REWARDS, abs_diff, end_to_end_angle, is_success, node_errors, orientation_error,
                            pairwise_shape_term, reward, reward_abs_diff, reward_delta_gain,
                            reward_position_orientation, reward_shape_gain, shape_error, within_tolerance,
                            worst_node_error)
from .planar.shapes import TARGET_FAMILIES, TARGET_NAMES, TargetError, random_curve, random_shape, target_shape
from .planar.simulator import MoveInfo, SimulationError, Simulator
from . import envs  # registers DiffDLO/ShapeControl-v0

__version__ = "0.1.0"     # setup.cfg reads it from here

__all__ = [
    "CableParams", "KernelUnavailableWarning", "MoveInfo", "ParamsError", "Physics", "REWARDS", "SimulationError", "Simulator",
    "TARGET_FAMILIES", "TARGET_NAMES", "TargetError", "abs_diff", "end_to_end_angle", "energy", "internal_forces",
    "is_success", "load_params", "node_errors", "orientation_error", "pairwise_shape_term", "random_curve",
    "random_shape", "reward", "reward_abs_diff", "reward_delta_gain", "reward_position_orientation",
    "reward_shape_gain", "shape_error", "target_shape", "turning_angles", "within_tolerance", "worst_node_error",
]
