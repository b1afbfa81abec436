"""Writes the fixed routing layouts (diffdlo/tasks/layouts/*.yaml) for the 20-node, 0.5 m rope of params/cable.yaml, or
draws them (each with the start of episode 0 beside it, and four random boards of target "route"):

    python -m diffdlo.tasks.layouts.make_layouts
    python -m diffdlo.tasks.layouts.make_layouts --figure docs/figures/layouts.png

Each route is a polyline of the rope's links built from its turning angles (degrees per interior node, node 1 to
N - 2), centred on the board; each peg sits against the inside (the route wraps it) or the outside (the route
passes it) of the route's turn at one node (diffdlo.tasks.routing.peg_against). The ones a learner trains on, and the
held-out ones (diffdlo.tasks.routing.HELD_OUT_LAYOUTS), which no learner may see in training.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
import yaml

from diffdlo.planar.params import load_params
from diffdlo.tasks.routing import HELD_OUT_LAYOUTS, Layout, peg_against, random_layout, start_beside
from diffdlo.planar.shapes import polyline_from_angles
from diffdlo.utils.files import check_fresh_file

HERE = Path(__file__).resolve().parent

# name: (turns [deg] per interior node (18 for 20 nodes), heading of link 0 [deg], [(node, radius [m], outside)])
LAYOUTS = {
    # a hairpin round two pegs side by side
    "u_two_pegs": ([0] * 6 + [36] * 5 + [0] * 7, 0.0, [(7, 0.012, False), (10, 0.012, False)]),
    # a snake through three pegs, each bend round one, alternating sides
    "s_three_pegs": ([0, 0, 0] + [30] * 3 + [0, 0] + [-30] * 3 + [0, 0] + [30] * 3 + [0, 0], -45.0,
                     [(4, 0.01, False), (9, 0.01, False), (14, 0.01, False)]),
    # held out: a hook that wraps one peg (225 degrees of turn), then passes another on its right
    "hook_wrap": ([45] * 5 + [0] * 13, 0.0, [(3, 0.008, False), (12, 0.008, True)]),
    # held out: a zigzag past four pegs, wrapped on alternate sides
    "zigzag_four": ([0, 0] + [35, 35] + [0, 0] + [-35, -35] + [0, 0] + [35, 35] + [0, 0] + [-35, -35] + [0, 0], -20.0,
                    [(3, 0.008, False), (7, 0.008, False), (11, 0.008, False), (15, 0.008, False)]),
}


def build(name: str) -> Layout:
    p = load_params("cable")
    turns, heading, pegs = LAYOUTS[name]
    assert len(turns) == p.n_nodes - 2, (name, len(turns))
    angles = torch.tensor([heading] + turns, dtype=torch.float64).cumsum(0) * math.pi / 180
    route = polyline_from_angles(angles[None], p.rest_length)[0]
    layout = Layout(torch.stack([peg_against(route, node, r, p, outside) for node, r, outside in pegs]), route, name)
    return layout.check(p)


def figure(path: Path) -> Path:
    """The fixed layouts and four random boards, each route dashed among its pegs with a start beside it."""
    from diffdlo.utils import render
    p = load_params("cable")
    layouts = [build(name) for name in LAYOUTS]
    gen = torch.Generator().manual_seed(0)
    layouts += [random_layout(p, gen) for _ in range(4)]
    starts = [start_beside(layout, p, torch.Generator().manual_seed(i)) for i, layout in enumerate(layouts)]
    titles = [f"{'held out: ' if layout.name in HELD_OUT_LAYOUTS else ''}{layout.name} ({len(layout.pegs)} pegs)"
              for layout in layouts]
    render.plot_ropes(torch.stack(starts), torch.stack([layout.route for layout in layouts]), path, titles=titles,
                      align_target=False, pegs=[layout.pegs for layout in layouts], cols=4)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffdlo.tasks.layouts.make_layouts", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--figure", type=Path, help="draw the layouts to this PNG instead of writing them")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --figure")
    args = parser.parse_args(argv)
    if args.figure is not None:
        try:
            check_fresh_file(args.figure, args.overwrite)
        except FileExistsError as exc:
            print(exc, file=sys.stderr)
            return 2
        print(f"wrote {figure(args.figure)}")
        return 0
    for name in LAYOUTS:
        layout = build(name)
        text = (f"# routing layout {name!r} for the 20-node, 0.5 m rope "
                f"(python -m diffdlo.tasks.layouts.make_layouts)\n"
                + yaml.safe_dump({"pegs": [[round(v, 6) for v in row] for row in layout.pegs.tolist()],
                                  "route": [[round(v, 6) for v in row] for row in layout.route.tolist()]},
                                 default_flow_style=None, sort_keys=False))
        (HERE / f"{name}.yaml").write_text(text)
        turns = ", ".join(f"{t / math.pi:+.2f} pi" for t in layout.turns().tolist())
        print(f"{name}: {len(layout.pegs)} pegs, the route turns {turns} round them")
    return 0


if __name__ == "__main__":
    sys.exit(main())
