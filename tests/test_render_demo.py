"""Pictures are written, and the README's demo runs."""
import pytest
import torch

import diffdlo

pytest.importorskip("matplotlib")
from diffdlo.tasks import demo
from diffdlo.utils import render  # noqa: E402


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


def test_pictures_are_readable_and_tell_their_lines_apart(params, tmp_path):
    """At most four panels a row, each at least 3 inches; one legend naming rope, target, node 0 and the grasped
    node; the error in each title; a GIF of episodes one after another, one target and title per frame."""
    sim = diffdlo.Simulator(params)
    pos = sim.random_shape(6, torch.Generator().manual_seed(1))
    targets = torch.stack([sim.target_shape("diagonal")] * 6)
    fig = render.plot_ropes(pos, targets, titles=[f"ep {i}" for i in range(6)], cols=8, size=1.0,
                            errors=[0.0123] * 6, grasped=[3, -1, 0, 5, 2, 1])
    panels = [ax for ax in fig.axes if ax.axison]
    assert len(panels) == 6
    assert len({round(ax.get_position().x0, 3) for ax in panels}) == 4                   # four columns, not eight
    width, height = fig.get_size_inches()
    assert width / 4 >= 3.0 and height / 2 >= 3.0
    assert panels[0].get_title() == "ep 0\nshape error 1.23 cm"
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert {"rope", "rope node 0", "target node 0", "grasped node"} <= set(labels)
    import matplotlib.pyplot as plt
    plt.close(fig)
    frames, per_frame_targets = torch.cat([pos[:1]] * 3 + [pos[1:2]] * 2), torch.cat([targets[:3], targets[3:5]])
    path = render.save_gif(frames, tmp_path / "episodes.gif", per_frame_targets, fps=4,
                           title=["start", "move 1", "move 2", "start", "move 1"], grasped=[-1, 2, 4, -1, 0])
    assert path.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    with pytest.raises(ValueError, match="one title per frame"):
        render.save_gif(frames, tmp_path / "x.gif", per_frame_targets, title=["only one"])
