"""How far the 3-D task's `recorded` targets (docs/CABLE3D.md) are from anything at rest: for each cable, the target
frames' speeds (the fastest free marker, m/s: DEFORM's cables are never still) and the fitted chain's rest shape with
its grippers exactly where the real cable's were in that frame, against the recorded markers: the mean and worst
marker errors and how many frames that rest shape would already count as a success (mean < 1 cm, worst < 2 cm).
What a planner reaches beyond that it reaches by putting the grippers elsewhere.

    python -m benchmarks.cable3d_recorded --data DEFORM/data_set
    python -m benchmarks.cable3d_recorded --data DEFORM/data_set --out docs/results/cable3d_recorded_static.json \
        --overwrite
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from diffdlo.chain3d import grippers as gr
from diffdlo.chain3d.cables import cable_names, load_cable
from diffdlo.chain3d.deform import RecordingError
from diffdlo.tasks import cable3d as rules
from diffdlo.utils.files import write_json_atomic


def static_errors(data: Path, name: str, settle_time: float = 10.0) -> dict:
    cable = load_cable(name)
    recorded = rules.recorded_targets(data, cable)
    frames = torch.stack([recorded.recordings[r][k] for r, k in recorded.targets])
    poses = gr.poses_of(frames)
    with torch.no_grad():
        rest = gr.settle(rules.hang(poses, cable), None, poses, cable, rest_speed=0.01, check_frames=10,
                         settle_frames=rules.frames_of(settle_time, "settle_time"))
    errors = rules.marker_errors(rest.x, frames)
    mean, worst = errors.mean(-1), errors.amax(-1)
    ok = (mean < 0.01) & (worst < 0.02)
    q = lambda t: [round(float(v), 4) for v in torch.quantile(t, torch.tensor([0.1, 0.5, 0.9], dtype=t.dtype))]
    return {"cable": name, "targets": len(recorded.targets), "at_rest": int(rest.settled.sum()),
            "speed_m_per_s_q10_50_90": q(torch.tensor(recorded.speeds, dtype=torch.float64)),
            "mean_error_cm_q10_50_90": [round(100 * v, 2) for v in q(mean)],
            "worst_error_cm_q10_50_90": [round(100 * v, 2) for v in q(worst)],
            "within_success_tolerance": int(ok.sum())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.cable3d_recorded", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="DEFORM's data_set folder")
    ap.add_argument("--cables", nargs="+", default=cable_names(), choices=cable_names())
    ap.add_argument("--out", type=Path, default=None, help="also write the rows here (JSON)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    args = ap.parse_args(argv)
    if args.out is not None and args.out.exists() and not args.overwrite:
        ap.error(f"--out {args.out} exists: give --overwrite to replace it, or another --out")
    rows = []
    print("| cable | targets | their speed [m/s] (10 / 50 / 90 %) | the chain at rest at the recorded grippers: mean "
          "error [cm] (10 / 50 / 90 %) | worst [cm] | already a success |\n|---|---|---|---|---|---|")
    for name in args.cables:
        try:
            row = static_errors(args.data, name)
        except (RecordingError, ValueError) as exc:
            ap.error(str(exc))
        rows.append(row)
        fmt = lambda v: " / ".join(f"{x:g}" for x in v)
        print(f"| {name} | {row['targets']} | {fmt(row['speed_m_per_s_q10_50_90'])} | "
              f"{fmt(row['mean_error_cm_q10_50_90'])} | {fmt(row['worst_error_cm_q10_50_90'])} | "
              f"{row['within_success_tolerance']} of {row['targets']} |")
    if args.out is not None:
        write_json_atomic(args.out, {"command": "python -m benchmarks.cable3d_recorded --data DEFORM/data_set",
                                     "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
