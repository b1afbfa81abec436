"""The learned residual correction on DEFORM's real cables (issue 61; docs/REAL_CABLE.md), reported apart from the
physics-only fit it starts from.

    python -m benchmarks.real_cable_residual --data /path/to/DEFORM/data_set --physics runs/real_cable \
        --out runs/real_cable_residual [--cables 1 2 3 4 5] [--jobs 2] [--seed 0] [--quick]

For each cable: the physical parameters are the physics-only fit's (``--physics``: a ``python -m
benchmarks.real_cable`` output folder; its results.json), held fixed; the residual network
(diffdlo.chain3d.residual.fit_residual) is trained through the chain's rollout over ``--window``-frame windows of the
train split, ``--validation`` of the train recordings held out (seeded) to keep its best state; then every eval
recording is predicted by DEFORM's protocol, physics only and with the correction, and scored.

Writes OUT/results.json (per cable: both errors, the paper's numbers, the training's record, the time per frame),
OUT/DLO<k>_residual.pt (the network: data only, ``diffdlo.chain3d.residual.load``), OUT/predictions/DLO<k>/<id>.npz
(``positions`` (T-2, n, 3) float32 [m] with the correction, frames 2..T-1) and OUT/figures/error_over_time.png.
The recordings are read from --data, never copied.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import shlex
import sys
import time
from pathlib import Path

import torch

from benchmarks.real_cable import PAPER_CM, plot_errors, write_predictions
from diffdlo.chain3d import deform, fit, residual
from diffdlo.utils.files import check_fresh_out, out_lock, write_json_atomic

# the helper study's settings (docs/REAL_CABLE.md: window 40 beat 20 on DLO3's validation and eval error)
FULL = dict(iterations=150, window=40, batch=8, lr=5e-3, eval_every=25, validation=8)
QUICK = dict(iterations=2, window=5, batch=2, lr=5e-3, eval_every=1, validation=2)


def physics_values(run: Path, name: str) -> dict[str, float]:
    """The physics-only fit's values of cable ``name`` from a benchmarks.real_cable results.json."""
    path = run / "results.json"
    if not path.is_file():
        raise ValueError(f"--physics {str(run)!r} holds no results.json (run python -m benchmarks.real_cable first)")
    cables = json.loads(path.read_text()).get("cables") or {}
    if name not in cables:
        raise ValueError(f"--physics {str(path)!r} has no fit of {name} (it has {sorted(cables)})")
    return {k: float(cables[name]["parameters"][k]["value"]) for k in fit.FIT_NAMES}


def train_one(data: str, cable: int, values: dict[str, float], settings: dict, seed: int, progress: bool
              ) -> tuple[residual.ResidualResult, list[str], list[str]]:
    """One cable's residual (in a worker process of one thread): trained on the train split less the validation
    recordings (drawn with ``seed``)."""
    torch.set_num_threads(1)
    spec = deform.CABLES[cable]
    train = deform.load_split(data, cable, "train")
    model = fit.cable_model(train, deform.HELD_MARKERS, mass=spec.mass, length=spec.length)
    ids = sorted(train)
    perm = torch.randperm(len(ids), generator=torch.Generator().manual_seed(seed)).tolist()
    k = min(settings["validation"], len(ids) - 1)
    val_ids, tr_ids = [ids[i] for i in perm[:k]], [ids[i] for i in perm[k:]]
    result = residual.fit_residual(
        model, values, {i: train[i] for i in tr_ids}, iterations=settings["iterations"], window=settings["window"],
        batch=settings["batch"], lr=settings["lr"], eval_every=settings["eval_every"], seed=seed,
        validation={i: train[i] for i in val_ids} if k else None, progress=progress, desc=spec.name)
    return result, tr_ids, val_ids


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.real_cable_residual", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="DEFORM's data_set folder")
    ap.add_argument("--physics", required=True, help="a benchmarks.real_cable output folder (its physics-only fit)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--cables", nargs="+", type=int, default=sorted(deform.CABLES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="cables trained at once, one process of one thread each")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the evaluation (timed)")
    for key, v in FULL.items():
        ap.add_argument("--" + key.replace("_", "-"), type=type(v), help=f"default {v}")
    ap.add_argument("--quick", action="store_true", help="a smoke run: a few tiny steps")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    data, physics = Path(args.data), Path(args.physics)
    if not data.is_dir():
        ap.error(f"--data {args.data!r} is not a folder (give DEFORM's data_set folder)")
    bad = [c for c in args.cables if c not in deform.CABLES]
    if bad or len(set(args.cables)) != len(args.cables):
        ap.error(f"--cables {args.cables} must name DEFORM cables {sorted(deform.CABLES)}, each once")
    settings = dict(QUICK if args.quick else FULL)
    for key in FULL:
        v = getattr(args, key)
        if v is not None:
            if v <= 0 and key != "validation" or v < 0:
                ap.error(f"--{key.replace('_', '-')} must be positive, got {v}")
            settings[key] = v
    if args.jobs < 1 or args.threads < 1:
        ap.error(f"--jobs and --threads must be at least 1, got {args.jobs} and {args.threads}")
    try:
        values = {c: physics_values(physics, deform.CABLES[c].name) for c in args.cables}
        check_fresh_out(args.out, args.overwrite, "an earlier residual benchmark")
        evals = {c: deform.load_split(data, c, "eval") for c in args.cables}
    except (ValueError, FileExistsError, deform.RecordingError) as exc:
        ap.error(str(exc))
    given = sys.argv[1:] if argv is None else argv
    command = "python -m benchmarks.real_cable_residual " + " ".join(shlex.quote(a) for a in given)
    out = Path(args.out)
    t0 = time.perf_counter()
    with out_lock(out):
        if args.jobs <= 1 or len(args.cables) <= 1:
            trained = {c: train_one(str(data), c, values[c], settings, args.seed, not args.no_progress)
                       for c in args.cables}
        else:
            ctx = multiprocessing.get_context("spawn")
            with concurrent.futures.ProcessPoolExecutor(max_workers=args.jobs, mp_context=ctx) as pool:
                futures = {c: pool.submit(train_one, str(data), c, values[c], settings, args.seed, False)
                           for c in sorted(args.cables, key=lambda c: -len(deform.load_split(data, c, "train")))}
                trained = {c: futures[c].result() for c in args.cables}
        train_s = time.perf_counter() - t0
        torch.set_num_threads(args.threads)
        cables = {}
        for c in args.cables:
            spec = deform.CABLES[c]
            result, tr_ids, val_ids = trained[c]
            model = fit.cable_model(deform.load_split(data, c, "train"), deform.HELD_MARKERS, mass=spec.mass,
                                    length=spec.length)
            repeats = 1 if args.quick else 3
            physics_only, _ = residual.evaluate(model, values[c], None, evals[c], repeats=repeats)
            ours, pred = residual.evaluate(model, values[c], result.net, evals[c], repeats=repeats)
            ids = list(evals[c])
            write_predictions(out, c, ids, pred)
            residual.save(result, out / f"{spec.name}_residual.pt", meta={"cable": spec.name})
            cables[spec.name] = {
                "ours": ours, "physics_only": physics_only, "frozen": fit.score(
                    fit.frozen_prediction(evals[c], deform.HELD_MARKERS), evals[c]),
                "paper_cm": {m: v[c - 1] for m, v in PAPER_CM.items()}, "physics_values": values[c],
                "training": {"settings": result.settings, "best_step": result.best_step, "skipped": result.skipped,
                             "seconds": result.seconds, "history_m": result.history,
                             "validation_m": [list(v) for v in result.validation], "train_ids": tr_ids,
                             "validation_ids": val_ids},
                "eval_ids": ids}
        below = {n: c["ours"]["l1_m"] * 100 < c["paper_cm"]["DEFORM"] for n, c in cables.items()}
        write_json_atomic(out / "results.json", {
            "command": command, "physics_run": str(physics), "settings": settings, "seed": args.seed,
            "jobs": args.jobs, "eval_threads": args.threads, "train_wall_s": train_s,
            "wall_s": time.perf_counter() - t0, "quick": args.quick, "below_deform": below, "cables": cables})
        try:
            plot_errors(cables, out / "figures" / "error_over_time.png",
                        label="chain + learned residual", extra=("physics_only", "chain, physics only"))
        except ImportError:
            print("matplotlib is not installed (the plot extra): no figures", file=sys.stderr)
    print("| cable | physics only [cm] | with the residual [cm] | DEFORM (paper) [cm] | DER (paper) [cm] | "
          "ms/frame (batched) | best step |")
    print("|---|---|---|---|---|---|---|")
    for n, c in cables.items():
        print(f"| {n} | {100 * c['physics_only']['l1_m']:.3f} | {100 * c['ours']['l1_m']:.3f} | "
              f"{c['paper_cm']['DEFORM']:.2f} | {c['paper_cm']['DER']:.2f} | {1e3 * c['ours']['time_per_frame_s']:.3f} | "
              f"{c['training']['best_step']} |")
    print(f"below DEFORM on every cable: {all(below.values())}; train {train_s:.0f} s, total "
          f"{time.perf_counter() - t0:.0f} s -> {out}/results.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
