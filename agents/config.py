"""The options every learner shares, as dataclasses composed into each learner's config, and how configs are read.

A learner's config (e.g. ``agents.sac.SACConfig``) holds ``task: TaskOptions`` (the env: target, observations,
actions, reward, the episode-end rules), ``run: RunOptions`` (budget, seed, devices, evaluation, checkpoints) and,
for SAC and PPO, ``inputs: InputOptions`` (how observations become network inputs), then its algorithm's own fields.
YAML files (``params/<algo>.yaml``) and ``--set`` name every option by its own flat name (``target``, ``seed``,
``lr``...): the names are unique across the parts, and ``from_flat`` puts each where it belongs.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
import yaml

from diffdlo.checks import check_interval
from diffdlo.params import PARAMS_DIR, CableParams, load_params   # one folder: cable params and presets
from diffdlo.rewards import REWARDS
from diffdlo.task import ACTION_TYPES, COORDINATE_OBS, EXIT_RULES, OBS_TYPES, PICTURE_OBS, resolve_target

SECTIONS = ("task", "run", "inputs")
ENCODERS = ("nature", "keypoints")
POLICIES = ("hybrid", "gaussian")


def _positive_int(key: str, v: Any, least: int = 1) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < least:
        raise ValueError(f"{key} must be a{' positive' if least == 1 else ' non-negative'} integer, got {v!r}")


def _is(kind: str, v: Any) -> bool:
    if kind in ("Any", "Callable"):
        return True
    if kind == "None":
        return v is None
    if kind == "int":
        return isinstance(v, int) and not isinstance(v, bool)
    if kind == "float":
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    return isinstance(v, {"bool": bool, "str": str, "list": list, "dict": dict}.get(kind, object))


def check_types(part) -> None:
    """Every option holds a value of its declared type (e.g. ``--set lr=abc`` is named, not trained with)."""
    for f in dataclasses.fields(part):
        if f.name in SECTIONS:
            continue
        kinds = [k.strip() for k in str(f.type).split("|")]
        v = getattr(part, f.name)
        if not any(_is(k, v) for k in kinds):
            wanted = "true or false" if kinds == ["bool"] else " or ".join(kinds)
            raise ValueError(f"{f.name} must be {wanted}, got {v!r} ({type(v).__name__})")


def check_ranges(part, ranges: dict[str, str]) -> None:
    """Each named option (None: not set, skipped) within its interval, written "[lo, hi]" / "(lo, hi)" / mixed,
    with inf for no bound; the message names the option, the interval and the value."""
    for key, interval in ranges.items():
        if getattr(part, key) is not None:
            check_interval(key, getattr(part, key), interval)


def check_layer_sizes(key: str, v: Any) -> None:
    if not isinstance(v, list) or not all(_is("int", x) and x >= 1 for x in v):
        raise ValueError(f"{key} must be a list of positive layer sizes, e.g. [256, 256], got {v!r}")


def _choice(key: str, v: Any, allowed) -> None:
    if v not in allowed:
        raise ValueError(f"unknown {key} {v!r}: use one of {list(allowed)}")


@dataclasses.dataclass
class TaskOptions:
    """The env a learner trains and is evaluated on (diffdlo.envs.BatchedShapeControl's arguments)."""
    target: Any = "random"
    obs: str = "points"
    action: str = "node"
    reward: str = "position_orientation"
    max_steps: int | None = None          # actions per episode (None: params' 100)
    params: str = "cable"
    param_overrides: dict | None = None   # e.g. {n_nodes: 6, length: 0.15} for quick tests
    start: Any = None                     # None (random start) or a .npy path / (N, 2) list: a fixed start shape
    success_tol: float | None = None      # None: params' 0.01 m
    image_size: int = 64
    success_bonus: float | None = None    # None: params' 20 (Algorithm 2)
    step_penalty: float = 0.0
    on_exit: str = "truncate"             # "fail": leaving the workspace terminates the episode
    exit_penalty: float = 0.0
    curve_max_turn_deg: float = 12.0      # target "random_curve": the largest turn per node [deg]
    mark_end: bool = False                # images: a dot on node 0 of rope and target (env option)
    perception: str | None = None         # obs "perceived": a checkpoint of python -m diffdlo.perception
    perception_refine: int | None = None  # its refinement steps per picture (None: the checkpoint's; 0: net alone)

    def check(self) -> None:
        check_types(self)
        check_ranges(self, {"max_steps": "[1, inf)", "perception_refine": "[0, inf)", "success_tol": "(0, inf)", "image_size": "[8, inf)",
                            "success_bonus": "(-inf, inf)", "step_penalty": "(-inf, inf)",
                            "exit_penalty": "(-inf, inf)", "curve_max_turn_deg": "[0, 90]"})
        _choice("obs type", self.obs, OBS_TYPES)
        _choice("action type", self.action, ACTION_TYPES)
        _choice("reward", self.reward, REWARDS)
        _choice("on_exit", self.on_exit, EXIT_RULES)
        if not isinstance(self.mark_end, bool):
            raise ValueError(f"mark_end must be true or false, got {self.mark_end!r}")
        if self.obs != "perceived" and self.perception_refine is not None:
            raise ValueError(f"perception_refine is read only by obs 'perceived', got obs {self.obs!r}")
        if (self.obs == "perceived") != (self.perception is not None):
            raise ValueError(f"obs 'perceived' and perception=PATH go together (a checkpoint of python -m "
                             f"diffdlo.perception), got obs {self.obs!r} and perception {self.perception!r}")
        if self.perception is not None:
            from diffdlo.perception import Perception
            Perception.load(self.perception, image_size=self.image_size, n_nodes=self.cable_params().n_nodes)
        po = self.param_overrides
        if po is not None:
            fields = {f.name for f in dataclasses.fields(CableParams)}
            if not isinstance(po, dict) or set(po) - fields:
                raise ValueError(f"param_overrides must map CableParams fields ({sorted(fields)}) to values, got "
                                 f"{po!r} (YAML flow maps need a space after each colon: {{n_nodes: 6}})")
        resolve_target(self.target, self.cable_params())     # a bad target or params file is named before any run

    def cable_params(self) -> CableParams:
        """The run's cable parameters, resolved once (params file, then param_overrides) and passed down."""
        p = load_params(self.params)
        return dataclasses.replace(p, **self.param_overrides) if self.param_overrides else p


@dataclasses.dataclass
class RunOptions:
    """Budget, seed, devices, evaluation and checkpoints of a run."""
    total_steps: int = 100_000            # env transitions, all envs together
    num_envs: int = 16
    seed: int = 0
    device: str = "cpu"                   # networks and buffer
    env_device: str = ""                  # the simulator ("": same as device; "cpu" with device "cuda": fused CPU kernel)
    threads: int = 1                      # torch CPU threads during training (restored afterwards)
    eval_every: int = 10_000
    eval_episodes: int = 20
    eval_seed: int = 10_000
    eval_targets: list = dataclasses.field(default_factory=list)   # held-out targets evaluated at the end
    checkpoint_every: int = 10_000
    log_every: int = 100                  # updates (SAC, PlaNet) or rollouts (PPO) between train-loss rows
    rollout_candidates: int = 0           # > 0: the final evaluations act by policy rollouts (agents/rollout.py)
    rollout_moves: int = 20               # their horizon: moves the policy finishes each candidate with

    def check(self) -> None:
        check_types(self)
        for key in ("total_steps", "num_envs", "threads", "eval_every", "eval_episodes", "checkpoint_every",
                    "log_every"):
            _positive_int(key, getattr(self, key))
        _positive_int("rollout_candidates", self.rollout_candidates, least=0)
        _positive_int("rollout_moves", self.rollout_moves, least=0)
        for key in ("device", "env_device"):
            v = getattr(self, key)
            if key == "env_device" and not v:
                continue                      # "": the learner's device
            try:
                dev = torch.device(v)
            except (RuntimeError, TypeError) as exc:
                raise ValueError(f"{key} must be a torch device such as 'cpu' or 'cuda', got {v!r}") from exc
            if dev.type == "cuda" and not torch.cuda.is_available():
                raise ValueError(f"{key}={v!r}: CUDA is not available on this machine")


@dataclasses.dataclass
class InputOptions:
    """How observations become network inputs (agents/networks.py ``Features``): target-relative features
    (agents/hybrid.py), optionally running-normalized, or SB3's encoder (flattened floats, a CNN on images)."""
    features: str = "raw"                 # "relative" | "raw"
    normalize_obs: bool = False           # running mean/std of the features (relative features only)
    cnn_channels: list = dataclasses.field(default_factory=lambda: [32, 64, 64])
    features_dim: int = 256
    encoder: str = "nature"               # images: "nature" (SB3 NatureCNN) | "keypoints" (spatial softmax)
    keypoints: int = 32                   # encoder "keypoints": feature maps -> 2 x keypoints coordinates
    augment_shift: int = 0                # images: DrQ random shift of up to this many pixels (0: off)

    def check(self, task: TaskOptions) -> None:
        check_types(self)
        check_layer_sizes("cnn_channels", self.cnn_channels)
        check_ranges(self, {"features_dim": "[1, inf)"})
        _choice("features", self.features, ("relative", "raw"))
        _choice("encoder", self.encoder, ENCODERS)
        if self.features == "relative" and task.obs not in COORDINATE_OBS:
            raise ValueError(f"features 'relative' need obs {list(COORDINATE_OBS)}, got {task.obs!r} "
                             "(use --set features=raw for images)")
        if self.normalize_obs and self.features != "relative":
            raise ValueError("normalize_obs needs features 'relative' (images and raw observations are not normalized)")
        _positive_int("keypoints", self.keypoints)
        _positive_int("augment_shift", self.augment_shift, least=0)


def check_model_free(cfg) -> None:
    """The checks SAC's and PPO's configs share: their task, run and input options, the policy head, the type of
    every own field and the hidden layer sizes."""
    cfg.task.check()
    cfg.run.check()
    cfg.inputs.check(cfg.task)
    check_policy(cfg.policy, cfg.task)
    check_types(cfg)
    check_layer_sizes("hidden", cfg.hidden)


def check_policy(policy: str, task: TaskOptions) -> None:
    """SAC's and PPO's policy head: "hybrid" (node categorical + per-node drag) needs node actions."""
    _choice("policy", policy, POLICIES)
    if policy == "hybrid" and task.action != "node":
        raise ValueError(f"policy 'hybrid' chooses a node: it needs action 'node', got {task.action!r} "
                         "(use --set policy=gaussian for pixel actions)")


def part(cls, **defaults):
    """A learner config's field holding a ``cls`` (TaskOptions, RunOptions, InputOptions) with these defaults."""
    return dataclasses.field(default_factory=lambda: cls(**defaults))


# ====================================================================== flat names <-> the composed config
def _section_fields(cls) -> dict[str, str]:
    """flat option name -> the section that holds it ("" for the learner's own fields)."""
    owner: dict[str, str] = {}
    for f in dataclasses.fields(cls):
        if f.name in SECTIONS:
            for g in dataclasses.fields(f.default_factory()):
                owner[g.name] = f.name
        else:
            owner[f.name] = ""
    return owner


def flat_names(cls) -> list[str]:
    return sorted(_section_fields(cls))


def _field_types(cls) -> dict[str, str]:
    types = {}
    for f in dataclasses.fields(cls):
        if f.name in SECTIONS:
            types.update({g.name: str(g.type) for g in dataclasses.fields(f.default_factory())})
        else:
            types[f.name] = str(f.type)
    return types


def _coerced(kind: str, v: Any) -> Any:
    """YAML reads 1e-3 (no dot) as a string: a string that is a number becomes one where the option is a float."""
    if isinstance(v, str) and "float" in kind:
        try:
            return float(v)
        except ValueError:
            return v
    return v


def from_flat(cls, values: dict[str, Any], base=None):
    """A config ``cls`` from flat option names (YAML, ``--set``), on top of ``base`` (default: cls's defaults).
    Also takes the nested form of ``to_dict`` (sections as dicts). Unknown names raise ValueError."""
    owner, types = _section_fields(cls), _field_types(cls)
    values = {k: ({k2: _coerced(types.get(k2, ""), v2) for k2, v2 in v.items()} if k in SECTIONS and
                  isinstance(v, dict) else _coerced(types.get(k, ""), v)) for k, v in values.items()}
    base = cls() if base is None else base
    top: dict[str, Any] = {}
    parts: dict[str, dict[str, Any]] = {}
    unknown = []
    for key, v in values.items():
        if key in SECTIONS and isinstance(v, dict) and hasattr(base, key):
            for k2, v2 in v.items():
                (parts.setdefault(key, {}).__setitem__(k2, v2) if owner.get(k2) == key else unknown.append(k2))
        elif key not in owner:
            unknown.append(key)
        elif owner[key]:
            parts.setdefault(owner[key], {})[key] = v
        else:
            top[key] = v
    if unknown:
        raise ValueError(f"unknown config keys {sorted(unknown)} for {cls.__name__}: allowed {flat_names(cls)}")
    sections = {s: dataclasses.replace(getattr(base, s), **kv) for s, kv in parts.items()}
    return dataclasses.replace(base, **top, **sections)


def flat_value(cfg, key: str) -> Any:
    """The value of an option of a config by its flat name."""
    section = _section_fields(type(cfg)).get(key)
    if section is None:
        raise ValueError(f"unknown config key {key!r} for {type(cfg).__name__}: allowed {flat_names(type(cfg))}")
    return getattr(getattr(cfg, section) if section else cfg, key)


def replace(cfg, **values):
    """``dataclasses.replace`` by flat option names: ``replace(cfg, target="diagonal", lr=1e-3)``."""
    return from_flat(type(cfg), values, base=cfg)


def to_dict(cfg) -> dict[str, Any]:
    """The nested dict of a config (what a checkpoint stores); ``from_flat`` reads it back."""
    return dataclasses.asdict(cfg)


# ====================================================================== presets and YAML files
def preset_path(algo: str, preset: str | None) -> Path:
    """``params/<algo>.yaml`` for the preset "tuned" (the default), ``params/<algo>-<preset>.yaml`` otherwise."""
    if preset in (None, "tuned"):
        return PARAMS_DIR / f"{algo}.yaml"
    path = PARAMS_DIR / f"{algo}-{preset}.yaml"
    if not path.exists():
        known = ["tuned"] + sorted(p.stem[len(algo) + 1:] for p in PARAMS_DIR.glob(f"{algo}-*.yaml"))
        raise ValueError(f"unknown preset {preset!r} for {algo}: use one of {known}")
    return path


def load_config(cls, name: str | Path, overrides: dict[str, Any] | None = None):
    """Config ``cls`` from ``params/<name>.yaml`` (or a YAML path) then ``overrides`` (flat names), checked.

    An ``obs`` override to pictures ("image", "image_single") takes the file's points-only input options with it
    (features "relative" -> "raw", normalize_obs -> false) unless the overrides set them too: ``--obs image`` alone
    trains the image encoder instead of failing on a points preset."""
    path = Path(name) if str(name).endswith((".yaml", ".yml")) else PARAMS_DIR / f"{name}.yaml"
    if not path.exists():
        raise ValueError(f"config file {str(path)!r} does not exist")
    values = yaml.safe_load(path.read_text()) or {}
    overrides = dict(overrides or {})
    if overrides.get("obs") in PICTURE_OBS and values.get("features") == "relative":
        overrides.setdefault("features", "raw")
        overrides.setdefault("normalize_obs", False)
    values.update(overrides)
    cfg = from_flat(cls, values)
    cfg.check()
    return cfg
