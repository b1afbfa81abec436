"""Rules pinned by hand-computed cases, each written against a one-line bug the rest of the suite let pass:

* eq 2.6's node is round(a0 (N - 1)), not floor (diffdlo/tasks/task.py decode_node);
* the ensemble world model is equivariant under translations and rotations: its prediction, made in the grasped
  node's frame, is rotated back with the inverse rotation (agents/models/ensemble.py);
* the Levenberg-Marquardt step uses its damping (diffdlo/calibration/calibrate.py Linearization.step).
"""
import math

import pytest
import torch

from agents.models.ensemble import EnsembleDynamics
from diffdlo.calibration.calibrate import Linearization
from diffdlo.planar.params import load_params
from diffdlo.tasks.task import decode_node, decode_node_action, encode_node_action


def test_the_node_is_rounded_not_floored():
    # N = 20: a0 (N - 1) = 0, 0.494, 0.513, 9.5, 18.43, 18.81, 19  ->  round: 0, 0, 1, 10 (half to even), 18, 19, 19
    a0 = torch.tensor([0.0, 0.026, 0.027, 0.5, 0.97, 0.99, 1.0])
    assert decode_node(a0, 20).tolist() == [0, 0, 1, 10, 18, 19, 19]
    assert decode_node(torch.tensor([-0.3, 1.7]), 20).tolist() == [0, 19]               # clipped first
    # every node survives encode -> decode, and the middle of each node's interval too
    p = load_params("cable")
    nodes = torch.arange(p.n_nodes)
    a = encode_node_action(nodes, torch.zeros(p.n_nodes, 2), p.n_nodes, p.action_scale)
    assert decode_node_action(a, p)[0].tolist() == nodes.tolist()
    off = (nodes.double() + 0.45) / (p.n_nodes - 1)                                     # 0.45 past each node
    assert decode_node(off.clamp(max=1.0), p.n_nodes).tolist() == nodes.tolist()


@pytest.mark.parametrize("frame", ["grasp", "centroid"])
def test_the_world_model_moves_with_the_rope(frame):
    """Translate and rotate the rope and the drag: the prediction is translated and rotated the same way (the grasp
    frame builds both in; the centroid frame only the translation)."""
    torch.manual_seed(0)
    p = load_params("cable")
    model = EnsembleDynamics(p, members=2, hidden=(16, 16), frame=frame).double()
    g = torch.Generator().manual_seed(1)
    rope = 0.1 * torch.randn(3, p.n_nodes, 2, generator=g, dtype=torch.float64)
    node = torch.tensor([0, 7, 19])
    drag = 0.05 * torch.randn(3, 2, generator=g, dtype=torch.float64)
    shift = torch.tensor([0.3, -0.2], dtype=torch.float64)
    moved = model(rope + shift, node, drag)
    torch.testing.assert_close(moved, model(rope, node, drag) + shift, rtol=0, atol=1e-12)
    if frame == "grasp":
        t = math.radians(73.0)
        rot = torch.tensor([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]], dtype=torch.float64)
        turned = model(rope @ rot.T, node, drag @ rot.T)
        torch.testing.assert_close(turned, model(rope, node, drag) @ rot.T, rtol=0, atol=1e-12)


def _dense_damped_step(lin: Linearization, lam: float) -> torch.Tensor:
    """-(H + lam diag(H))^-1 g of the whole dense system (theta, then every move's start)."""
    s, m, d, _ = lin.j_theta.shape
    k = lin.j_start.shape[-1]
    dense = torch.zeros(m * d, 4 + m * k, dtype=torch.float64)
    for i in range(m):
        dense[i * d:(i + 1) * d, :4] = lin.j_theta[0, i]
        dense[i * d:(i + 1) * d, 4 + i * k:4 + (i + 1) * k] = lin.j_start[0, i]
    h = dense.T @ dense
    h = h + lam * torch.diag(h.diagonal()) + 1e-12 * torch.eye(h.shape[0], dtype=torch.float64)
    return -torch.linalg.solve(h, dense.T @ lin.r[0].flatten())


def test_the_levenberg_marquardt_step_is_damped():
    g = torch.Generator().manual_seed(0)
    m, d, k = 3, 12, 4                                       # 3 moves, 12 residuals each, starts of 2 nodes
    lin = Linearization(torch.randn(1, m, d, generator=g, dtype=torch.float64),
                        torch.randn(1, m, d, 4, generator=g, dtype=torch.float64),
                        torch.randn(1, m, d, k, generator=g, dtype=torch.float64), m * d)
    steps = {}
    for lam in (0.0, 0.5, 100.0):
        d_theta, d_start = lin.step(torch.tensor([lam], dtype=torch.float64))
        expected = _dense_damped_step(lin, lam)
        torch.testing.assert_close(d_theta[0], expected[:4], rtol=1e-7, atol=1e-10)
        torch.testing.assert_close(d_start[0].flatten(), expected[4:], rtol=1e-7, atol=1e-10)
        steps[lam] = float(d_theta.norm())
    assert steps[100.0] < steps[0.5] < steps[0.0]            # more damping, a shorter step
    # without starts: the 4 x 4 system alone
    lin4 = Linearization(lin.r, lin.j_theta, None, m * d)
    h = lin.j_theta[0].transpose(-1, -2) @ lin.j_theta[0]
    h, grad = h.sum(0), (lin.j_theta[0].transpose(-1, -2) @ lin.r[0].unsqueeze(-1)).sum(0).squeeze(-1)
    d_theta, _ = lin4.step(torch.tensor([2.0], dtype=torch.float64))
    expected = -torch.linalg.solve(h + 2.0 * torch.diag(h.diagonal()) + 1e-12 * torch.eye(4, dtype=torch.float64),
                                   grad)
    torch.testing.assert_close(d_theta[0], expected, rtol=1e-7, atol=1e-10)
