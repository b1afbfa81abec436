"""How well the perception reads ropes among pegs (the routing task's pictures), with and without the pegs drawn.

    python -m benchmarks.studies.perception_pegs --out runs/perception_pegs
    python -m benchmarks.studies.perception_pegs --perception models/perception64.pt models/perception64_pegs.pt --out runs/perception_pegs

Held-out pictures (``--seed``, 7 by default: no training of the committed checkpoints drew from it), ``--pictures``
of each kind, on random boards (diffdlo.tasks.routing.random_layout) drawn as the routing env draws them (64 px, end
markers, grey pegs under the rope; diffdlo.perception.boards): the env's starts beside and across the board, ropes
after 1-8 random moves among the pegs, ropes lying on the route near its pegs (the end of an episode), and the routes
themselves in the target's palette (the route picture); and each fixed layout's route picture and a rope lying on
that route (one picture each). Each set is also drawn WITHOUT the pegs (the same ropes), and the old held-out set of
the checkpoint's training (seed 1: ropes and targets without pegs) is read too.

Readings: the network alone; + ``--refine`` analysis-by-synthesis steps (60: the checkpoint's) whose synthesized
pictures draw no pegs (as before the pegs were known to it) or the same pegs (``Perception.read(..., pegs=)``, what
the env and the planners do now); and the network on the picture with the known pegs taken out (``unpeg``, what
``Perception.read(..., pegs=)`` does), refined with the pegs drawn. Error: mean node distance to the truth per
picture [mm]; mean and 95th percentile (one number for a single picture).
Prints a table and writes ``<out>/results.json`` (an existing one only with ``--overwrite``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from diffdlo.planar.params import load_params
from diffdlo.perception import (Perception, PerceptionError, TrainConfig, held_out, node_error, refine, render_uint8,
                                unpeg)
from diffdlo.tasks import routing
from diffdlo.perception.boards import BOARD_KINDS, MAX_PEGS, board_shapes
from diffdlo.planar.simulator import Simulator

KINDS = BOARD_KINDS + ("route",)          # "route": the target picture of the route, with its pegs
READINGS = ("net", "refined_blind", "refined", "net_unpegged", "refined_unpegged")


def picture_sets(n: int, seed: int, p, sim, size: int, view_size: float) -> dict[str, dict[str, torch.Tensor]]:
    """Per kind: truth (n, N, 2), pegs (n, K, 3), rope (bool), pictures with and without the pegs."""
    g = torch.Generator().manual_seed(seed)
    sets = {}
    for kind in BOARD_KINDS:
        ropes, pegs, routes = board_shapes(n, p, g, sim, kind)
        sets[kind] = dict(truth=ropes.float(), pegs=pegs.float(), rope=True)
        if kind == "beside":            # the route pictures: the boards of the starts beside them
            sets["route"] = dict(truth=routes.float(), pegs=pegs.float(), rope=False)
    sets = {k: sets[k] for k in KINDS}
    for name in routing.layout_names():         # the fixed layouts: the route picture, and a rope lying on the route
        lay = routing.load_layout(name, p)
        route, pegs = lay.route[None].float(), routing.padded(lay.pegs, MAX_PEGS)[None].float()
        sets[f"{name}: route"] = dict(truth=route, pegs=pegs, rope=False)
        sets[f"{name}: rope on it"] = dict(truth=sim.settle(route.to(sim.dtype), pegs=pegs.to(sim.dtype)).float(),
                                                 pegs=pegs, rope=True)
    for s in sets.values():
        s["with_pegs"] = render_uint8(s["truth"], size, view_size, s["rope"], s["pegs"])
        s["no_pegs"] = render_uint8(s["truth"], size, view_size, s["rope"])
    return sets


def errors(perception: Perception, images: torch.Tensor, truth: torch.Tensor, rope: bool, pegs: torch.Tensor | None,
           iters: int, chunk: int = 64) -> dict[str, torch.Tensor]:
    """Per picture node errors [m] of the network alone and refined without / with the pegs drawn."""
    out: dict[str, list[torch.Tensor]] = {r: [] for r in READINGS}
    for i in range(0, len(images), chunk):
        im, tr = images[i:i + chunk], truth[i:i + chunk]
        pg = None if pegs is None else pegs[i:i + chunk]
        with torch.no_grad():
            guess = perception.net(im)
        out["net"].append(node_error(guess, tr))
        kw = dict(iters=iters)
        out["refined_blind"].append(node_error(refine(guess, im, perception.rest_length, perception.view_size, rope,
                                                      **kw), tr))
        if pg is not None:
            out["refined"].append(node_error(refine(guess, im, perception.rest_length, perception.view_size, rope,
                                                    pegs=pg, **kw), tr))
            with torch.no_grad():
                clean = perception.net(unpeg(im, pg, perception.view_size, rope))
            out["net_unpegged"].append(node_error(clean, tr))
            out["refined_unpegged"].append(node_error(refine(clean, im, perception.rest_length, perception.view_size,
                                                             rope, pegs=pg, **kw), tr))
    return {k: torch.cat(v) for k, v in out.items() if v}


def summary(e: torch.Tensor) -> dict[str, float]:
    return {"mean_mm": 1000 * float(e.mean()), "p95_mm": 1000 * float(e.quantile(0.95)), "n": len(e)}


def measure(path: str, sets, old, iters: int) -> tuple[dict, dict[str, torch.Tensor]]:
    """The checkpoint's summaries, and its per-picture errors of the readings the env makes now (for pairing)."""
    perception = Perception.load(path, image_size=64, view_size=1.0)
    t0 = time.perf_counter()
    res: dict = {"checkpoint": path, "kinds": {}}
    per_picture: dict[str, torch.Tensor] = {}
    pooled: dict[str, dict[str, list]] = {"with_pegs": {r: [] for r in READINGS}, "no_pegs": {r: [] for r in READINGS}}
    for kind, s in sets.items():
        res["kinds"][kind] = {}
        for drawn in ("with_pegs", "no_pegs"):
            e = errors(perception, s[drawn], s["truth"], s["rope"], s["pegs"] if drawn == "with_pegs" else None,
                       iters)
            res["kinds"][kind][drawn] = {r: summary(v) for r, v in e.items()}
            if drawn == "with_pegs":
                per_picture[kind] = e["refined_unpegged"]
            if kind in BOARD_KINDS:
                for r, v in e.items():
                    pooled[drawn][r].append(v)
    res["ropes_among_pegs"] = {d: {r: summary(torch.cat(v)) for r, v in rs.items() if v} for d, rs in pooled.items()}
    res["old_held_out"] = {}
    for key, images, truth, rope in (("ropes", old["rope_images"], old["ropes"], True),
                                     ("targets", old["target_images"], old["targets"], False)):
        e = errors(perception, images, truth, rope, None, iters)
        res["old_held_out"][key] = {r: summary(v) for r, v in e.items()}
        per_picture[f"old held-out {key}"] = e["refined_blind"]
    per_picture["all ropes among pegs"] = torch.cat([per_picture[k] for k in BOARD_KINDS])
    res["wall_s"] = time.perf_counter() - t0
    return res, per_picture


def paired(first: dict[str, torch.Tensor], other: dict[str, torch.Tensor], resamples: int = 4000) -> dict[str, dict]:
    """Per set: the mean of (other - first) per-picture errors [mm] on the same pictures, with a 95 % bootstrap
    interval (``resamples`` resamplings of the pictures, generator seed 0)."""
    out = {}
    for key, a in first.items():
        d = other[key] - a
        idx = torch.randint(0, len(d), (resamples, len(d)), generator=torch.Generator().manual_seed(0))
        means = d[idx].mean(1)
        out[key] = {"mean_mm": 1000 * float(d.mean()), "low_mm": 1000 * float(means.quantile(0.025)),
                    "high_mm": 1000 * float(means.quantile(0.975)), "n": len(d)}
    return out


def fmt(s: dict | None) -> str:
    if s is None:
        return "—"
    return f"{s['mean_mm']:.1f}" if s["n"] == 1 else f"{s['mean_mm']:.2f} / {s['p95_mm']:.1f}"


def table(results: list[dict], iters: int) -> str:
    head = (f"| checkpoint | pictures | no pegs drawn: network | no pegs drawn: + {iters} steps | pegs drawn: network "
            f"| pegs drawn: + {iters} steps, synthesis without pegs | pegs drawn: + {iters} steps, synthesis with pegs "
            f"| pegs drawn: network on the picture with the pegs taken out (unpeg) | pegs drawn: unpeg, then + {iters} "
            "steps, synthesis with pegs |")
    lines = [head, "|" + "---|" * 9]
    for r in results:
        name = Path(r["checkpoint"]).name
        rows = [(k, r["kinds"][k]) for k in KINDS] + [("all ropes among pegs", r["ropes_among_pegs"])] + \
               [(k, v) for k, v in r["kinds"].items() if k not in KINDS]
        for kind, v in rows:
            n, w = v["no_pegs"], v["with_pegs"]
            lines.append(f"| {name} | {kind} | {fmt(n['net'])} | {fmt(n['refined_blind'])} | {fmt(w['net'])} | "
                         f"{fmt(w['refined_blind'])} | {fmt(w['refined'])} | {fmt(w['net_unpegged'])} | "
                         f"{fmt(w['refined_unpegged'])} |")
        for key in ("ropes", "targets"):
            v = r["old_held_out"][key]
            lines.append(f"| {name} | old held-out {key} (seed 1, no pegs) | {fmt(v['net'])} | {fmt(v['refined_blind'])} "
                         "| — | — | — | — | — |")
    return "\n".join(lines) + "\n\nEach cell: mean / 95th percentile of the per-picture mean node error [mm]."


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.perception_pegs", description=__doc__.split("\n\n")[0])
    ap.add_argument("--perception", nargs="+", default=["models/perception64.pt"], help="checkpoint(s) to measure")
    ap.add_argument("--pictures", type=int, default=128, help="pictures of each kind (default 128)")
    ap.add_argument("--seed", type=int, default=7, help="the held-out pictures' seed (default 7: no training drew it)")
    ap.add_argument("--refine", type=int, default=60, help="refinement steps (default 60, the checkpoint's)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    ap.add_argument("--out", default=None, help="folder for results.json (none: print only)")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier results.json in --out")
    args = ap.parse_args(argv)
    if args.pictures < 2 or args.refine < 0 or args.threads < 1:
        ap.error(f"--pictures must be >= 2, --refine >= 0, --threads >= 1, got {args.pictures}, {args.refine}, "
                 f"{args.threads}")
    out = None if args.out is None else Path(args.out) / "results.json"
    if out is not None and out.exists() and not args.overwrite:
        ap.error(f"{out} exists: pass --overwrite to replace it")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    p = load_params("cable")
    sim = Simulator(p)
    t0 = time.perf_counter()
    sets = picture_sets(args.pictures, args.seed, p, sim, 64, 1.0)
    old = held_out(p, TrainConfig(image_size=64, eval_pictures=256, seed=0), sim, 1.0)
    try:
        measured = [measure(path, sets, old, args.refine) for path in args.perception]
    except PerceptionError as exc:
        ap.error(f"--perception: {exc}")
    results = [r for r, _ in measured]
    text = table(results, args.refine)
    pairs = {}
    for path, (_, errs) in zip(args.perception[1:], measured[1:]):
        pairs[path] = paired(measured[0][1], errs)
        text += (f"\n\n{Path(path).name} against {Path(args.perception[0]).name}, the same pictures (the env's reading: "
                 f"unpeg, then {args.refine} steps drawing the pegs; without pegs: {args.refine} steps): mean difference "
                 "of the per-picture error [mm], 95 % bootstrap interval\n\n| pictures | difference [mm] |\n|---|---|\n")
        text += "\n".join(f"| {k} | {v['mean_mm']:+.2f} [{v['low_mm']:+.2f}, {v['high_mm']:+.2f}] |"
                           for k, v in pairs[path].items())
    print(text)
    if out is not None:
        from diffdlo.utils.files import write_json_atomic
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out, {"results": results, "paired": pairs, "table": text, "pictures": args.pictures,
                                "seed": args.seed,
                                "refine": args.refine, "threads": args.threads, "wall_s": time.perf_counter() - t0,
                                "command": "python -m benchmarks.studies.perception_pegs " + " ".join(
                                    sys.argv[1:] if argv is None else argv)})
        print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
