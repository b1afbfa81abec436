"""The routing task's rules (diffdlo/tasks/routing.py): the side test on hand-made ropes (one that matches the route's
shape but passes a peg on the wrong side), the layouts (shipped, drawn, checked) and the start beside the board."""
import math

import pytest
import torch

import diffdlo
from diffdlo.planar import contact
from diffdlo.tasks import routing
from diffdlo.tasks.layouts import make_layouts
from diffdlo.tasks.routing import Layout, LayoutError

F64 = torch.float64


@pytest.fixture(scope="module")
def p():
    return diffdlo.load_params("cable")


def line(p, y=0.0):
    return diffdlo.target_shape("horizontal", p, dtype=F64) + torch.tensor([0.0, y], dtype=F64)


def test_winding_tells_the_sides_of_a_peg_apart(p):
    rope = line(p)[None]
    above, below = torch.tensor([[0.0, 0.02]], dtype=F64), torch.tensor([[0.0, -0.02]], dtype=F64)
    w_above, w_below = float(routing.winding(rope, above)[0, 0]), float(routing.winding(rope, below)[0, 0])
    assert w_above > 0.8 * math.pi and w_below < -0.8 * math.pi       # left to right under a peg: counter-clockwise
    assert abs(w_above - w_below) > 1.6 * math.pi
    circle = torch.stack([torch.cos(torch.linspace(0, 2 * math.pi * 0.95, 20)),
                          torch.sin(torch.linspace(0, 2 * math.pi * 0.95, 20))], -1).double() * 0.08
    assert float(routing.winding(circle[None], torch.zeros(1, 2, dtype=F64))[0, 0]) == pytest.approx(1.9 * math.pi)


def test_a_rope_of_the_routes_shape_on_the_wrong_side_of_a_peg_fails_the_side_test(p):
    """The same straight shape above a peg the route passes below: zero shape error, wrong side. And a rope within
    the distance tolerance (a 2-node detour over a thin peg, 1.7 mm mean error) on the wrong side fails it too."""
    route = line(p)
    pegs = torch.tensor([[0.0, 0.02, 0.01]], dtype=F64)
    Layout(pegs, route, "test").check(p)
    shifted = line(p, 0.04)
    assert float(diffdlo.shape_error(shifted[None], route[None])) < 1e-12
    assert not bool(routing.sides_kept(shifted[None], route[None], pegs[None]))
    assert bool(routing.sides_kept(line(p, -0.01)[None], route[None], pegs[None]))
    thin = torch.tensor([[0.0, 0.0085, 0.002]], dtype=F64)
    Layout(thin, route, "thin").check(p)
    detour = route.clone()
    detour[9:11, 1] = 0.0085 + 0.002 + p.rope_radius + 0.0015
    assert float(contact.depth(detour[None], thin[None], p.rope_radius)) < 0          # an admissible rope
    assert float(routing.route_errors(detour[None], route).mean()) < 0.002
    assert not bool(routing.sides_kept(detour[None], route[None], thin[None]))
    assert bool(routing.sides_kept(route[None], route[None], thin[None]))


def test_the_shipped_layouts_load_and_match_their_maker(p):
    names = routing.layout_names()
    assert set(names) == set(make_layouts.LAYOUTS) and set(routing.HELD_OUT_LAYOUTS) < set(names)
    for name in names:
        layout = routing.load_layout(name, p)
        built = make_layouts.build(name)
        torch.testing.assert_close(layout.pegs, built.pegs, rtol=0, atol=1e-6)
        torch.testing.assert_close(layout.route, built.route, rtol=0, atol=1e-6)
        turns = layout.turns()
        assert bool((turns.abs() > 0.8 * math.pi).all()), (name, turns)          # every peg really passed
        assert bool(routing.sides_kept(layout.route[None], layout.route[None], layout.pegs[None]))
    assert (routing.load_layout("u_two_pegs", p).turns() > 1.5 * math.pi).all()    # the U wraps both
    s = routing.load_layout("s_three_pegs", p).turns()
    assert bool((s[:-1] * s[1:] < 0).all())                                           # alternating sides


@pytest.mark.parametrize("change, match", [
    (lambda pegs, route: (torch.cat([pegs, pegs[:1] + torch.tensor([[0.005, 0.0, 0.0]], dtype=F64)]), route),
     r"pegs 0 \[.*\] and 2 \[.*\] \(rope 0\) leave a gap of -19 mm between them, less than the rope's diameter "
     r"\(10 mm\)"),
    (lambda pegs, route: (pegs, route[:-1]), r"must have shape \(20, 2\).*got \(19, 2\)"),
    (lambda pegs, route: (pegs, route * 1.2), r"link \d+ \(nodes \d+-\d+\) is 0.0316 m long, but the rope's links are 0.0263 m"),
    (lambda pegs, route: (torch.tensor([[0.0, 0.012, 0.01]], dtype=F64), line(diffdlo.load_params("cable"))),
     r"the route's link 9-10 runs 3 mm into peg 0 \[0.0, 0.012, 0.01\]"),
    (lambda pegs, route: (pegs[:0], route), r"K >= 1 \(a route needs a peg\), got shape \(0, 3\)"),
    (lambda pegs, route: (pegs * torch.tensor([1.0, 1.0, -1.0], dtype=F64), route), r"radius must be > 0 m"),
])
def test_a_bad_layout_is_refused_naming_the_value(p, change, match):
    u = routing.load_layout("u_two_pegs", p)
    pegs, route = change(u.pegs, u.route)
    with pytest.raises(LayoutError, match=match):
        Layout(pegs, route, "bad").check(p)


def test_load_layout_refuses_unknown_names_and_bad_files(p, tmp_path):
    with pytest.raises(LayoutError, match=r"no layout 'nope': use one of \['hook_wrap'"):
        routing.load_layout("nope", p)
    bad = tmp_path / "bad.yaml"
    bad.write_text("pegs: [[0, 0, 0.01]]\n")
    with pytest.raises(LayoutError, match="must hold 'pegs' and 'route'"):
        routing.load_layout(bad, p)
    bad.write_text("pegs: [[0, 0, x]]\nroute: [[0, 0]]\n")
    with pytest.raises(LayoutError, match="arrays of numbers"):
        routing.load_layout(bad, p)


def test_random_layouts_are_valid_reproducible_and_varied(p):
    layouts = [routing.random_layout(p, torch.Generator().manual_seed(seed)) for seed in range(20)]
    again = routing.random_layout(p, torch.Generator().manual_seed(3))
    assert torch.equal(again.pegs, layouts[3].pegs) and torch.equal(again.route, layouts[3].route)
    counts = [len(lay.pegs) for lay in layouts]
    assert set(counts) == {2, 3, 4}
    for lay in layouts:
        lay.check(p)
        assert bool((lay.turns().abs() >= routing.MIN_TURN).all())
        assert float((lay.pegs[:, :2].abs() + lay.pegs[:, 2:]).max()) <= routing.BOARD / 2
    wrapped = sum(int((lay.turns().abs() > 1.5 * math.pi).sum()) for lay in layouts)
    passed = sum(int((lay.turns().abs() < 1.3 * math.pi).sum()) for lay in layouts)
    assert wrapped > 5 and passed > 5                      # some pegs wrapped, some passed


def test_a_start_beside_the_board_is_clear_of_the_pegs_and_off_the_route(p):
    for seed in range(10):
        g = torch.Generator().manual_seed(seed)
        layout = routing.random_layout(p, g)
        start = routing.start_beside(layout, p, g)
        assert float(contact.depth(start[None], layout.pegs[None], p.rope_radius)) < 0
        assert float(routing.route_errors(start[None], layout.route).mean()) > 0.05
        diffdlo.Simulator(p, dtype=F64).move(start[None], torch.tensor([0]), torch.zeros(1, 2, dtype=F64),
                                             layout.pegs)           # an admissible start


def test_the_layout_maker_draws_and_refuses_to_overwrite(tmp_path, capsys):
    figure = tmp_path / "layouts.png"
    assert make_layouts.main(["--figure", str(figure)]) == 0 and figure.stat().st_size > 10_000
    assert make_layouts.main(["--figure", str(figure)]) == 2 and "--overwrite" in capsys.readouterr().err


def test_clear_of_pegs_moves_a_rope_out_of_the_pegs_and_leaves_a_clear_one(p):
    """Ropes (random boards' routes, each node pulled up to 12 mm towards the nearest peg: links up to a peg's
    radius deep, some nodes inside) come out with every link's surface clear of every peg, the simulator takes them,
    no node moves farther than the depth it started at plus a link's sag, and a clear rope is returned as it was."""
    gen = torch.Generator().manual_seed(3)
    layouts = [routing.random_layout(p, gen) for _ in range(6)]
    slots = max(len(lay.pegs) for lay in layouts)
    pegs = torch.stack([routing.padded(lay.pegs.double(), slots) for lay in layouts])
    routes = torch.stack([lay.route.double() for lay in layouts])
    away = routes[:, :, None, :] - pegs[:, None, :, :2]
    dist = away.norm(dim=-1) + torch.where(pegs[:, None, :, 2] > 0, 0.0, 1e3)
    k = dist.argmin(-1)
    towards = -torch.gather(away, 2, k[..., None, None].expand(-1, -1, 1, 2))[:, :, 0] / dist.amin(-1)[..., None]
    pull = 0.012 * torch.rand(routes.shape[:2], generator=gen, dtype=F64)[..., None]
    ropes = routes + pull * towards
    before = contact.depth(ropes, pegs, p.rope_radius)
    assert float(before.max()) > p.rope_radius                       # deeper than the simulator takes
    cleared = routing.clear_of_pegs(ropes, pegs, p.rope_radius)
    assert float(contact.depth(cleared, pegs, p.rope_radius).max()) <= 1e-4
    assert float((cleared - ropes).norm(dim=-1).max()) < float(before.max()) + 0.005
    sim = diffdlo.Simulator(p, dtype=F64)
    moved = sim.move(cleared, torch.zeros(6, dtype=torch.long), torch.zeros(6, 2, dtype=F64), pegs)
    assert bool(torch.isfinite(moved).all())
    assert torch.equal(routing.clear_of_pegs(routes, pegs, p.rope_radius), routes)          # routes clear their pegs
