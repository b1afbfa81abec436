"""Pictures are written, and the README's demo runs."""
import pytest
import torch

import diffdlo

pytest.importorskip("matplotlib")
from diffdlo import demo, render  # noqa: E402


def test_plot_and_gif_are_written(params, tmp_path):
    sim = diffdlo.Simulator(params)
    pos = sim.random_shape(3, torch.Generator().manual_seed(0))
    target = sim.target_shape("diagonal")
    render.plot_ropes(pos, target, tmp_path / "ropes.png", titles=["a", "b", "c"])
    _, info = sim.move(pos[:1], torch.tensor([0]), torch.tensor([[0.03, 0.0]]), return_info=True,
                       record_every=200)
    assert info.frames.shape[1:] == (1, params.n_nodes, 2) and info.frames.shape[0] >= 3
    render.save_gif(info.frames[:, 0], tmp_path / "move.gif", target)
    assert (tmp_path / "ropes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "move.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")


def test_demo_writes_its_pictures(tmp_path, capsys):
    demo.main(["--out", str(tmp_path), "--moves", "2"])
    assert (tmp_path / "demo.png").stat().st_size > 1000
    assert (tmp_path / "demo.gif").stat().st_size > 1000
    assert "2 moves" in capsys.readouterr().out
