"""agents.distill: the student matches its teacher on a tiny case, the run resumes exactly, and a teacher that does
not fit is named."""
import json

import pytest
import torch

from agents import distill, ppo
from agents.common.config import from_flat
from agents.distill import Labels, fit, stored_action
from agents.common.envs import TrainEnv
from agents.common.logs import read_csv
from agents.tools.policy import load_policy
from diffdlo.envs import BatchedShapeControl
from diffdlo.planar.params import load_params
from diffdlo.tasks.task import encode_node_action, greedy_drags

from test_agents import TINY, argv as ppo_argv


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    out = tmp_path_factory.mktemp("teacher") / "ppo"
    assert ppo.main(ppo_argv("ppo", out, 128)) == 0
    return out


def distill_argv(teacher, out, total, *extra):
    return ["--out", str(out), "--total-steps", str(total), "--num-envs", "8", "--set", TINY, "--max-steps", "8",
            "--eval-every", "64", "--eval-episodes", "4", "--checkpoint-every", "64", "--no-progress",
            "--set", f"teacher={teacher}", "--set", "teacher_candidates=3", "--set", "teacher_moves=2",
            "--set", "fit_every=64", "--set", "teacher_every=64", "--set", "batch_size=32", *extra]


def test_the_student_matches_its_teacher_on_a_tiny_case():
    """A hand-written teacher (the greedy move: the farthest node toward its place) labels 64 states; fit on them,
    the student's mode grasps the teacher's node and drags as it does."""
    torch.manual_seed(0)
    p = load_params("cable")
    core = BatchedShapeControl(64, target="random", obs_type="points", action_type="node")
    obs = TrainEnv(core).reset(seed=3)
    drags, dist = greedy_drags(obs["node_poses"].double(), obs["target_poses"].double(), p.max_disp)
    node = dist.argmax(-1)
    moves = encode_node_action(node, drags[torch.arange(64), node], p.n_nodes, p.action_scale).float()
    labels = Labels()
    labels.add(obs, stored_action(moves, p.n_nodes))
    cfg = from_flat(ppo.PPOConfig, {"policy": "hybrid", "features": "relative", "hidden": [64, 64],
                                    "log_std_init": -3.0})
    student = ppo.ActorCritic(obs, 3, cfg, p.length, p.n_nodes)
    student.log_std.requires_grad_(False)
    opt = torch.optim.Adam([q for q in student.parameters() if q.requires_grad], lr=1e-2)
    before = fit(student, opt, labels, epochs=1, batch_size=64, device="cpu")
    after = fit(student, opt, labels, epochs=150, batch_size=64, device="cpu")
    assert after["imitation_loss"] < before["imitation_loss"]
    assert after["node_agreement"] == 1.0
    with torch.no_grad():
        acted = student.act(obs, deterministic=True)
    assert torch.equal(acted[:, 0], moves[:, 0])                       # the teacher's node ...
    assert (acted[:, 1:] - moves[:, 1:]).abs().max() < 0.05            # ... dragged as the teacher drags it


def test_distill_resumes_exactly_and_loads_as_a_policy(teacher, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert distill.main(distill_argv(teacher, a, 192)) == 0
    assert distill.main(distill_argv(teacher, b, 128)) == 0           # stopped after its checkpoint at 128
    assert distill.main(["--out", str(b), "--resume", "--total-steps", "192", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = (json.loads((d / "results.json").read_text()) for d in (a, b))
    assert ra["episodes"] == rb["episodes"] and ra["teacher_sim_evals"] == rb["teacher_sim_evals"] > 0
    rows = read_csv(a / "train.csv")
    assert [int(float(r["states"])) for r in rows] == [64, 128, 192]     # DAgger: the labelled set grows
    policy = load_policy(a)
    assert policy.algo == "distill" and policy.config.hidden == [32, 32]  # the teacher's network, rebuilt


def test_a_teacher_that_does_not_fit_is_named(teacher, tmp_path):
    with pytest.raises(ValueError, match="reads another task: param_overrides"):
        distill.teacher_checkpoint(from_flat(distill.DistillConfig, {"teacher": str(teacher)}))
    with pytest.raises(FileNotFoundError, match="no checkpoint there"):
        distill.teacher_checkpoint(from_flat(distill.DistillConfig, {"teacher": str(tmp_path / "none")}))
    with pytest.raises(ValueError, match="give the PPO run to distill"):
        from_flat(distill.DistillConfig, {}).check()
