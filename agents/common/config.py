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

from diffdlo.utils.checks import check_fields, field_kinds, option
from diffdlo.envs.options import EnvOptions, env_field
from diffdlo.planar.params import PARAMS_DIR, CableParams, load_params   # one folder: cable params and presets
from diffdlo.tasks.task import COORDINATE_OBS, PICTURE_OBS

SECTIONS = ("task", "run", "inputs")
ENCODERS = ("nature", "keypoints")
POLICIES = ("hybrid", "gaussian")


@dataclasses.dataclass
class TaskOptions:
    """The env a learner trains and is evaluated on: ``diffdlo.envs.EnvOptions`` by the learners' flat names (``obs``
    is its obs_type, ``action`` its action_type; each such field has EnvOptions' default, rule and help), with the
    cable params by name and their overrides. ``env_options`` maps it onto EnvOptions; ``check`` builds that."""
    target: Any = env_field("target")
    obs: str = env_field("obs_type")
    action: str = env_field("action_type")
    reward: str = env_field("reward")
    max_steps: int | None = env_field("max_steps")
    params: str = option("cable", help="cable params name (params/<name>.yaml) or YAML path")
    param_overrides: dict | None = option(None, help="CableParams fields replaced, e.g. {n_nodes: 6, length: 0.15}")
    start: Any = env_field("start")
    success_tol: float | None = env_field("success_tol")
    success_worst_tol: float | None = env_field("success_worst_tol")
    image_size: int = env_field("image_size")
    success_bonus: float | None = env_field("success_bonus")
    step_penalty: float = env_field("step_penalty")
    on_exit: str = env_field("on_exit")
    exit_penalty: float = env_field("exit_penalty")
    curve_max_turn_deg: float = env_field("curve_max_turn_deg")
    mark_end: bool = env_field("mark_end")
    perception: str | None = env_field("perception")
    perception_refine: int | None = env_field("perception_refine")

    def check(self) -> None:
        check_fields(self)                  # by the learners' names: "obs", and the rules' intervals
        po = self.param_overrides
        if po is not None:
            fields = {f.name for f in dataclasses.fields(CableParams)}
            if set(po) - fields:
                raise ValueError(f"param_overrides must map CableParams fields ({sorted(fields)}) to values, got "
                                 f"{po!r} (YAML flow maps need a space after each colon: {{n_nodes: 6}})")
        self.env_options().resolve()        # the env's own rules: a bad params file or target is named before any run
        if self.perception is not None:
            from diffdlo.perception import Perception
            Perception.load(self.perception, image_size=self.image_size, n_nodes=self.cable_params().n_nodes)

    def env_options(self, params: CableParams | None = None) -> EnvOptions:
        """The env's options of this task, with the run's resolved ``params`` (default: ``cable_params()``).
        ``max_episode_steps`` is the episode length, so gymnasium's time limit agrees."""
        p = self.cable_params() if params is None else params
        same = {f.metadata["env_name"]: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.metadata.get("env_name")}
        return EnvOptions(**same, params=p, max_episode_steps=self.max_steps or p.max_episode_steps)

    def cable_params(self) -> CableParams:
        """The run's cable parameters, resolved once (params file, then param_overrides) and passed down."""
        p = load_params(self.params)
        return dataclasses.replace(p, **self.param_overrides) if self.param_overrides else p


POSITIVE = dict(interval="[1, inf)", says="a positive integer")
NON_NEGATIVE = dict(interval="[0, inf)", says="a non-negative integer")


@dataclasses.dataclass
class RunOptions:
    """Budget, seed, devices, evaluation and checkpoints of a run."""
    total_steps: int = option(100_000, **POSITIVE, help="env transitions, all envs together")
    num_envs: int = option(16, **POSITIVE, help="ropes simulated in one batch")
    seed: int = option(0, help="seed of the networks, the buffer and the training envs")
    device: str = option("cpu", help="networks and buffer")
    env_device: str = option("", help='the simulator ("": same as device; "cpu" with device "cuda": fused CPU kernel)')
    threads: int = option(1, **POSITIVE, help="torch CPU threads during training (restored afterwards)")
    eval_every: int = option(10_000, **POSITIVE, help="env transitions between evaluations")
    eval_episodes: int = option(20, **POSITIVE, help="episodes per evaluation")
    eval_seed: int = option(10_000, help="evaluation episode i is seeded eval_seed + i")
    eval_targets: list = option(factory=list, help="held-out targets evaluated at the end")
    checkpoint_every: int = option(10_000, **POSITIVE, help="env transitions between checkpoints")
    log_every: int = option(100, **POSITIVE, help="updates (SAC, PlaNet) or rollouts (PPO) between train-loss rows")
    rollout_candidates: int = option(0, **NON_NEGATIVE,
                                     help="> 0: the final evaluations act by policy rollouts (agents/common/rollout.py)")
    rollout_moves: int = option(20, **NON_NEGATIVE, help="their horizon: moves the policy finishes each candidate with")

    def check(self) -> None:
        check_fields(self)
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
    """How observations become network inputs (agents/models/networks.py ``Features``): target-relative features
    (agents/models/hybrid.py), optionally running-normalized, or SB3's encoder (flattened floats, a CNN on images)."""
    features: str = option("raw", choices=("relative", "raw"),
                           help='"relative": target-relative features (agents/models/hybrid.py); "raw": SB3\'s encoder')
    normalize_obs: bool = option(False, help="running mean/std of the features (relative features only)")
    cnn_channels: list = option(factory=lambda: [32, 64, 64], layers=True, help="images: the CNN's channels")
    features_dim: int = option(256, "[1, inf)", help="images: the encoder's output size")
    encoder: str = option("nature", choices=ENCODERS,
                          help='images: "nature" (SB3 NatureCNN) | "keypoints" (spatial softmax)')
    keypoints: int = option(32, **POSITIVE, help='encoder "keypoints": feature maps -> 2 x keypoints coordinates')
    augment_shift: int = option(0, **NON_NEGATIVE, help="images: DrQ random shift of up to this many pixels (0: off)")

    def check(self, task: TaskOptions) -> None:
        check_fields(self)
        if self.features == "relative" and task.obs not in COORDINATE_OBS:
            raise ValueError(f"features 'relative' need obs {list(COORDINATE_OBS)}, got {task.obs!r} "
                             "(use --set features=raw for images)")
        if self.normalize_obs and self.features != "relative":
            raise ValueError("normalize_obs needs features 'relative' (images and raw observations are not normalized)")


def check_model_free(cfg, pin: bool = False) -> None:
    """The checks SAC's and PPO's configs share: their task, run and input options, every own field against the
    rule declared beside it, and the policy head against the actions (``pin``: the learner's hybrid head also
    chooses the second gripper's node, "node_pin" actions)."""
    cfg.task.check()
    cfg.run.check()
    cfg.inputs.check(cfg.task)
    check_fields(cfg, skip=SECTIONS)
    check_policy(cfg.policy, cfg.task, pin)


def check_policy(policy: str, task: TaskOptions, pin: bool = False) -> None:
    """SAC's and PPO's policy head (one of POLICIES, checked with the field): "hybrid" (node categorical + per-node
    drag) needs node actions ("node", or "node_pin" where the learner's head chooses the pin too)."""
    allowed = ("node", "node_pin") if pin else ("node",)
    if policy == "hybrid" and task.action not in allowed:
        hint = ("use --set policy=gaussian for pixel actions" if "pixel" in str(task.action) else
                "the second gripper's choice is PPO's hybrid head only (agents/ppo.py)")
        raise ValueError(f"policy 'hybrid' chooses a node: it needs action {' or '.join(map(repr, allowed))}, got "
                         f"{task.action!r} ({hint})")


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


def _flat_kinds(cls) -> dict[str, tuple[type, ...] | None]:
    """flat option name -> the types its annotation allows (None: any)."""
    kinds = {}
    for f in dataclasses.fields(cls):
        if f.name in SECTIONS:
            kinds.update(field_kinds(type(f.default_factory())))
        else:
            kinds[f.name] = field_kinds(cls)[f.name]
    return kinds


def _coerced(kinds: tuple[type, ...] | None, v: Any) -> Any:
    """YAML reads 1e-3 (no dot) as a string: a string that is a number becomes one where the option is a float."""
    if isinstance(v, str) and kinds is not None and float in kinds:
        try:
            return float(v)
        except ValueError:
            return v
    return v


def from_flat(cls, values: dict[str, Any], base=None):
    """A config ``cls`` from flat option names (YAML, ``--set``), on top of ``base`` (default: cls's defaults).
    Also takes the nested form of ``to_dict`` (sections as dicts). Unknown names raise ValueError."""
    owner, kinds = _section_fields(cls), _flat_kinds(cls)
    values = {k: ({k2: _coerced(kinds.get(k2), v2) for k2, v2 in v.items()} if k in SECTIONS and
                  isinstance(v, dict) else _coerced(kinds.get(k), v)) for k, v in values.items()}
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
