"""The perception among a route's pegs (docs/PERCEPTION.md, "Among pegs"): the pictures with pegs are the env's, the
known pegs are taken out of the network's input and drawn by the refinement, a route env's "perceived" observation
reads the rope with the committed checkpoint and carries the pegs exactly, and the planners plan a route from it."""
import json
from pathlib import Path

import pytest
import torch

from diffdlo.envs import BatchedShapeControl
from diffdlo.perception import (Perception, PerceptionError, TrainConfig, augmented_batch, node_error, refine,
                                render_uint8, unpeg)
from planners import cem as cem_mod
from planners import greedy as greedy_mod

CHECKPOINT = Path(__file__).parents[1] / "models" / "perception64.pt"
CHECKPOINT_PEGS = CHECKPOINT.with_name("perception64_pegs.pt")     # fine-tuned among pegs


def straight_rope_between_pegs(p):
    """A straight rope along x and three 20 mm pegs against it, 1 mm clear of its surface."""
    s = torch.linspace(-p.length / 2, p.length / 2, p.n_nodes)
    rope = torch.stack([s, torch.zeros_like(s)], -1)[None]
    gap = 0.02 + p.rope_radius + 0.001
    return rope, torch.tensor([[[-0.1, -gap, 0.02], [0.12, gap, 0.02], [0.0, -gap, 0.02]]])


def test_pictures_with_pegs_are_the_envs(one_thread):
    env = BatchedShapeControl(2, target="route", obs_type="image", mark_end=True, reward="route_gain")
    obs, _ = env.reset(seed=5)
    s = env.get_state(generators=False)
    assert torch.equal(render_uint8(s.pos, 64, 1.0, True, s.pegs), obs["image"])
    assert torch.equal(render_uint8(s.target, 64, 1.0, False, s.pegs), obs["target_image"])
    assert not torch.equal(render_uint8(s.pos, 64, 1.0, True), obs["image"])        # the pegs are in the picture


def test_unpeg_takes_the_known_pegs_out_of_the_pictures(params):
    rope, pegs = straight_rope_between_pegs(params)
    for line in (True, False):                         # the rope's palette and the target's
        drawn, bare = render_uint8(rope, 64, 1.0, line, pegs).int(), render_uint8(rope, 64, 1.0, line).int()
        out = unpeg(drawn.to(torch.uint8), pegs, 1.0, line).int()
        before, after = (drawn - bare).abs().sum(), (out - bare).abs().sum()
        assert (drawn - bare).abs().max() > 100 and after < 0.03 * before, (line, before, after)
        assert (out - bare).abs().max() <= 10
    empty = torch.zeros(1, 4, 3)                       # rows of zeros: no peg, nothing changes
    picture = render_uint8(rope, 64, 1.0)
    assert torch.equal(unpeg(picture, empty, 1.0), picture)


def test_refinement_drawing_the_pegs_beats_the_blind_one(params, one_thread):
    rope, pegs = straight_rope_between_pegs(params)
    picture = render_uint8(rope, 64, 1.0, True, pegs)
    start = rope + torch.tensor([0.0, 0.005]) + 0.003 * torch.randn(rope.shape, generator=torch.Generator().manual_seed(0))
    blind = node_error(refine(start, picture, params.rest_length, 1.0, iters=30), rope)
    known = node_error(refine(start, picture, params.rest_length, 1.0, iters=30, pegs=pegs), rope)
    assert known < 0.6 * blind and known < 0.002, (float(blind), float(known))


def test_a_route_env_perceives_the_rope_among_its_pegs_and_carries_them(one_thread):
    kw = dict(target="route", obs_type="perceived", perception=CHECKPOINT, reward="route_gain", route_start="across")
    env = BatchedShapeControl(2, **kw)
    obs, _ = env.reset(seed=3)
    s = env.get_state(generators=False)
    assert set(obs) == {"node_poses", "target_poses", "pegs"} and torch.equal(obs["pegs"], s.pegs.float())
    assert float(node_error(obs["node_poses"], s.pos).max()) < 0.005          # measured about 0.5 mm
    assert float(node_error(obs["target_poses"], s.target).max()) < 0.005
    assert env.single_observation_space.contains({k: v[0].numpy() for k, v in obs.items()})
    obs2, *_ = env.step(torch.tensor([[0.5, 0.7, 0.5], [0.2, 0.5, 0.3]], dtype=torch.float64))
    s2 = env.get_state(generators=False)
    assert torch.equal(obs2["pegs"], s2.pegs.float()) and float(node_error(obs2["node_poses"], s2.pos).max()) < 0.01
    again, _ = BatchedShapeControl(2, **kw).reset(seed=3)                       # same seed, same reading
    assert all(torch.equal(again[k], obs[k]) for k in obs)


def test_a_bad_board_is_named(one_thread):
    perception = Perception.load(CHECKPOINT, refine_iters=0)
    pictures = torch.full((2, 64, 64, 3), 255, dtype=torch.uint8)
    with pytest.raises(PerceptionError, match=r"pegs must be \(2, K, 3\).*got \(1, 4, 3\)"):
        perception.read(pictures, pegs=torch.zeros(1, 4, 3))
    with pytest.raises(PerceptionError, match="radius >= 0"):
        perception.read(pictures, pegs=torch.tensor([[[0.0, 0.0, -0.01]]]).expand(2, 1, 3))


def test_training_pictures_among_pegs_only_when_asked(params):
    pool = torch.randn(8, params.n_nodes, 2, dtype=torch.float64) * 0.05
    rope, _ = straight_rope_between_pegs(params)
    board_ropes = rope.double() * torch.linspace(0.5, 1.0, 4, dtype=torch.float64)[:, None, None]   # 4 lengths
    boards = (board_ropes, torch.tensor([[0.0, 0.1, 0.02], [0.1, -0.1, 0.015]], dtype=torch.float64).expand(4, 2, 3))
    cfg = TrainConfig(batch=6)
    plain = augmented_batch(pool, cfg, torch.Generator().manual_seed(1), 1.0)
    ignored = augmented_batch(pool, cfg, torch.Generator().manual_seed(1), 1.0, boards)   # pegs_share 0: unchanged
    assert all(torch.equal(a, b) for a, b in zip(plain, ignored))
    images, labels = augmented_batch(pool, TrainConfig(batch=6, pegs_share=1.0), torch.Generator().manual_seed(1),
                                     1.0, boards)
    grey = (images.int() - 110).abs().amax(-1) <= 20                                       # peg pixels
    assert bool(grey.flatten(1).any(1).all())
    total = (labels[:, 1:] - labels[:, :-1]).norm(dim=-1).sum(1)                # each a board rope, turned and placed
    board_total = (board_ropes[:, 1:] - board_ropes[:, :-1]).norm(dim=-1).sum(1).float()
    assert bool(((total[:, None] - board_total[None]).abs().amin(1) < 1e-4).all())


def test_a_planner_plans_a_route_from_the_perceived_rope(tmp_path, one_thread):
    out = tmp_path / "greedy"
    assert greedy_mod.main(["--target", "route:s_three_pegs", "--perception", str(CHECKPOINT), "--perception-refine",
                            "20", "--max-steps", "1", "--out", str(out), "--quiet", "--no-gif"]) == 0
    episode = json.loads((out / "results.json").read_text())["episodes"][0]
    assert episode["steps"] == 1 and len(episode["pegs"]) == 3
    assert 0 < episode["seen_error_mm"] < 5 and episode["seen_target_error_mm"] < 5, episode
    assert episode["seen_errors_mm"] == [pytest.approx(episode["seen_error_mm"], abs=0.01)]     # one move


def test_a_reading_inside_a_peg_is_projected_out_before_planning(tmp_path, one_thread, monkeypatch):
    """A reading a few mm inside a peg (the perception's error near a peg: CEM met a link 6.6 mm deep, more than the
    rope's radius the simulator allows, on episode 10000 from pictures) is projected out before the planner simulates
    from it: here every node of the rope within 3 cm of a peg's surface is read 1 mm inside that peg."""
    import planners.common as common
    deep = []

    def read_inside(points, perception, rope=True, pegs=None):
        if not rope:
            return points.clone()
        away = points[:, None, :] - pegs[None, :, :2]                         # (N, K, 2)
        dist = away.norm(dim=-1)
        near = (dist < pegs[:, 2] + 0.03) & (dist > 0)
        inside = pegs[None, :, :2] + away / dist[..., None] * (pegs[:, 2] - 0.001)[None, :, None]
        k = dist.argmin(1)
        moved = near[torch.arange(len(points)), k]
        deep.append(int(moved.sum()))
        return torch.where(moved[:, None], inside[torch.arange(len(points)), k], points)

    monkeypatch.setattr(common, "seen", read_inside)
    out = tmp_path / "cem"
    assert cem_mod.main(["--target", "route:s_three_pegs", "--route-start", "across", "--perception", str(CHECKPOINT_PEGS),
                         "--max-steps", "2", "--horizon", "1", "--candidates", "8", "--elites", "2", "--iterations",
                         "1", "--out", str(out), "--quiet", "--no-gif"]) == 0
    episode = json.loads((out / "results.json").read_text())["episodes"][0]
    assert episode["steps"] == 2 and min(deep) > 0, deep
