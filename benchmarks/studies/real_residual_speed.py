"""The learned residual's cost per trajectory-frame against physics only, on DEFORM's eval recordings (issue 61).

    python -m benchmarks.studies.real_residual_speed --data DEFORM/data_set --physics runs/real_cable \
        --residual runs/real_cable_residual [--threads 2]

For each cable: ``residual.evaluate`` (the 14 eval recordings batched, best of 3 full rollouts) with and without the
network saved by benchmarks.real_cable_residual (``<residual>/DLO<k>_residual.pt``), the physics values from the
benchmarks.real_cable run. Prints one line per cable; run it on a machine doing nothing else.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from diffdlo.chain3d import deform, fit, residual


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.real_residual_speed", description=__doc__)
    ap.add_argument("--data", required=True)
    ap.add_argument("--physics", required=True, help="a benchmarks.real_cable output folder")
    ap.add_argument("--residual", required=True, help="a benchmarks.real_cable_residual output folder")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    if args.threads < 1:
        ap.error(f"--threads must be at least 1, got {args.threads}")
    path = Path(args.physics) / "results.json"
    if not path.is_file():
        ap.error(f"--physics {args.physics!r} holds no results.json")
    phys = json.loads(path.read_text())["cables"]
    torch.set_num_threads(args.threads)
    for c in sorted(deform.CABLES):
        spec = deform.CABLES[c]
        net_path = Path(args.residual) / f"{spec.name}_residual.pt"
        if spec.name not in phys or not net_path.is_file():
            continue
        train, evals = deform.load_split(args.data, c, "train"), deform.load_split(args.data, c, "eval")
        model = fit.cable_model(train, deform.HELD_MARKERS, mass=spec.mass, length=spec.length)
        values = {k: phys[spec.name]["parameters"][k]["value"] for k in fit.FIT_NAMES}
        a, _ = residual.evaluate(model, values, None, evals, repeats=3)
        b, _ = residual.evaluate(model, values, residual.load(net_path), evals, repeats=3)
        print(f"{spec.name} substeps {model.substeps}: physics {1e3 * a['time_per_frame_s']:.3f} ms, with residual "
              f"{1e3 * b['time_per_frame_s']:.3f} ms per trajectory-frame ({args.threads} threads); "
              f"l1 {100 * b['l1_m']:.3f} cm", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
