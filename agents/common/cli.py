"""The learners' command line: one parser for the options every run shares, presets, ``--set``, ``--resume``."""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any, Callable

import yaml

from agents.common import config as config_lib
from agents.common.checkpoints import CHECKPOINT, load_checkpoint
from diffdlo.utils.signals import Interrupted, exit_code
from diffdlo.utils.files import OutBusyError
from diffdlo.planar.params import ParamsError
from diffdlo.tasks.rewards import REWARDS
from diffdlo.planar.shapes import TARGET_NAMES, TargetError
from diffdlo.tasks.task import ACTION_TYPES, OBS_TYPES, PICTURE_OBS


def positive_int(text: str) -> int:
    try:
        v = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


PRESET_DEFAULT = " (default: the preset's)"


def make_parser(prog: str, doc: str | None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0])
    ap.add_argument("--preset", default=None,
                    help="named defaults: 'tuned' (params/<algo>.yaml, the default) or e.g. 'sb3-default' "
                         "(params/<algo>-sb3-default.yaml)")
    ap.add_argument("--config", default=None, help="YAML of defaults (instead of a preset)")
    ap.add_argument("--target", default=None,
                    help=f"'random', 'random_curve', one of {list(TARGET_NAMES)} or a .npy/.yaml path" + PRESET_DEFAULT)
    ap.add_argument("--obs", choices=OBS_TYPES, default=None, help="observation type" + PRESET_DEFAULT)
    ap.add_argument("--action", choices=ACTION_TYPES, default=None, help="action type" + PRESET_DEFAULT)
    ap.add_argument("--reward", choices=REWARDS, default=None, help="reward function" + PRESET_DEFAULT)
    ap.add_argument("--total-steps", type=positive_int, default=None,
                    help="env transitions (all envs together)" + PRESET_DEFAULT)
    ap.add_argument("--num-envs", type=positive_int, default=None, help="ropes stepped together" + PRESET_DEFAULT)
    ap.add_argument("--seed", type=int, default=None, help="seed of everything" + PRESET_DEFAULT)
    ap.add_argument("--out", required=True, help="output directory (logs, checkpoint, results.json, pictures)")
    ap.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda" + PRESET_DEFAULT)
    ap.add_argument("--resume", action="store_true",
                    help="continue from <out>/checkpoint.pt up to --total-steps (config from the checkpoint; only "
                         "--total-steps, --eval-every, --eval-episodes, --checkpoint-every and --device may change)")
    ap.add_argument("--overwrite", action="store_true",
                    help="start afresh in an --out that holds an earlier run, replacing its logs and results")
    ap.add_argument("--eval-every", type=positive_int, default=None,
                    help="env steps between evaluations" + PRESET_DEFAULT)
    ap.add_argument("--eval-episodes", type=positive_int, default=None, help="episodes per evaluation" + PRESET_DEFAULT)
    ap.add_argument("--checkpoint-every", type=positive_int, default=None,
                    help="env steps between checkpoints" + PRESET_DEFAULT)
    ap.add_argument("--max-steps", type=positive_int, default=None, help="actions per episode" + PRESET_DEFAULT)
    ap.add_argument("--perception", default=None,
                    help="obs 'perceived': a perception checkpoint (python -m diffdlo.perception)" + PRESET_DEFAULT)
    ap.add_argument("--image-size", type=positive_int, default=None,
                    help="picture side [px] of image and perceived observations" + PRESET_DEFAULT)
    ap.add_argument("--params", default=None, help="cable params name or YAML path" + PRESET_DEFAULT)
    ap.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads" + PRESET_DEFAULT)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override any config key (YAML value), e.g. --set batch_size=128 --set hidden=[64,64]")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


RESUME_KEYS = ("total_steps", "eval_every", "eval_episodes", "checkpoint_every", "device")   # may change at --resume


def flag_options() -> tuple[str, ...]:
    """The flags that set a config option: each is named as an option of the task or the run (``--max-steps``:
    max_steps), so every learner takes the same ones."""
    options = {f.name for part in (config_lib.TaskOptions, config_lib.RunOptions) for f in dataclasses.fields(part)}
    return tuple(key for key in vars(make_parser("", None).parse_args(["--out", ""])) if key in options)


CLI_KEYS = flag_options()


def requested_options(args: argparse.Namespace, ap: argparse.ArgumentParser) -> dict[str, Any]:
    """The options the command line sets (flags and --set), by flat name."""
    overrides: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    for key in CLI_KEYS:
        v = getattr(args, key)
        if v is not None:
            overrides[key] = v
    return overrides


# The preset a picture observation takes when none is named: the default one cannot read pictures.
IMAGE_PRESETS = {"planet": "rssm"}


def config_from_args(cls, algo: str, args: argparse.Namespace, ap: argparse.ArgumentParser):
    if args.config and args.preset:
        ap.error("give --config or --preset, not both")
    if not (args.config or args.preset) and args.obs in PICTURE_OBS and algo in IMAGE_PRESETS:
        args.preset = IMAGE_PRESETS[algo]
        print(f"{algo}: --obs {args.obs} takes the preset {args.preset!r} (the default one reads points)",
              file=sys.stderr)
    try:
        return config_lib.load_config(cls, args.config or config_lib.preset_path(algo, args.preset),
                                      requested_options(args, ap))
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))


def resumed_config(cls, algo: str, args: argparse.Namespace, ap: argparse.ArgumentParser):
    """The checkpoint's config with the changes a resume may make; any other setting that differs from the
    checkpoint's is refused, by name (a resume continues THAT run)."""
    if args.preset or args.config:
        ap.error("--resume takes the config from the checkpoint: drop --preset/--config")
    try:
        ck = load_checkpoint(Path(args.out) / CHECKPOINT)
        if ck.get("algo") != algo:
            raise ValueError(f"{Path(args.out) / CHECKPOINT} is a checkpoint of {ck.get('algo')!r}, not of {algo}")
        cfg = config_lib.from_flat(cls, ck["config"])
    except (FileNotFoundError, ValueError, KeyError, TypeError) as exc:
        ap.error(f"--resume: {exc}")
    asked = requested_options(args, ap)
    differ = [f"{k} (the run's {config_lib.flat_value(cfg, k)!r}, asked {v!r})" for k, v in asked.items()
              if k not in RESUME_KEYS and config_lib.flat_value(cfg, k) != v]
    if differ:
        ap.error(f"--resume: these settings differ from the checkpoint's: {'; '.join(differ)}. A resume continues "
                 "the saved run: drop them, or start a new run in another --out")
    try:
        cfg = config_lib.replace(cfg, **{k: v for k, v in asked.items() if k in RESUME_KEYS})
        cfg.check()
    except (ValueError, TypeError) as exc:
        ap.error(f"--resume: {exc}")
    return cfg


def run_cli(cls, algo: str, doc: str | None, train: Callable, argv: list[str] | None = None) -> int:
    """Parse, build the config (or take it from the checkpoint with --resume), train, report."""
    ap = make_parser(f"python -m agents.{algo}", doc)
    args = ap.parse_args(argv)
    if args.resume and args.overwrite:
        ap.error("give --resume or --overwrite, not both")
    out = Path(args.out)
    cfg = resumed_config(cls, algo, args, ap) if args.resume else config_from_args(cls, algo, args, ap)
    try:
        res = train(cfg, out, resume=args.resume, progress=not args.no_progress, overwrite=args.overwrite)
    except (ValueError, TargetError, ParamsError, FileNotFoundError, FileExistsError, OutBusyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:            # Interrupted: stopped at a step with a checkpoint; else at once
        message = str(exc) if isinstance(exc, Interrupted) else \
            f"{algo}: interrupted: the last checkpoint in {out} is where --resume continues"
        print(message, file=sys.stderr)
        return exit_code(exc)
    print(f"{algo}: success rate {res['success_rate']:.2f} over {len(res['episodes'])} eval episodes, "
          f"{res['env_steps']} env steps, {res['wall_s']:.1f} s -> {out}/results.json")
    return 0
