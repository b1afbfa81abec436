import torch

import diffdlo
from diffdlo import image


def test_pixel_grid_and_world_to_pixel_agree():
    grid = image.pixel_centres(8, 1.0)
    assert grid.shape == (8, 8, 2)
    assert torch.allclose(grid[0, 0], torch.tensor([-0.5 + 1 / 16, 0.5 - 1 / 16]))      # top-left pixel
    colrow = image.world_to_pixel(grid, 8, 1.0)
    expect = torch.stack(torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="xy"), -1) + 0.5
    assert torch.allclose(colrow, expect, atol=1e-6)


def test_coverage_of_a_horizontal_segment():
    seg = torch.tensor([[[-0.3, 0.0], [0.3, 0.0]]])
    cov = image.coverage(seg, 64, 1.0, line_width=2 / 64)
    assert cov.shape == (1, 64, 64)
    assert cov.min() >= 0 and cov.max() <= 1
    # The line y = 0 lies on the boundary between rows 31 and 32: both are half-covered or more.
    assert (cov[0, 31:33, 20:44] >= 0.49).all()
    assert cov[0, :25].sum() == 0 and cov[0, 40:].sum() == 0        # far rows are empty
    assert cov[0, :, :8].sum() == 0                                 # left of the segment's end


def test_batched_render_equals_single_renders_and_colours():
    p = diffdlo.load_params("cable")
    ropes = diffdlo.random_shape(3, p, torch.Generator().manual_seed(0))
    target = diffdlo.target_shape("horizontal", p)
    imgs = image.render_ropes(ropes, target, size=48)
    assert imgs.shape == (3, 48, 48, 3) and imgs.dtype == torch.uint8
    for i in range(3):
        assert torch.equal(imgs[i], image.render_ropes(ropes[i:i + 1], target, size=48)[0])
    only_target = image.render_ropes(None, target.expand(1, -1, -1), size=48)[0]
    blue = (only_target == torch.tensor(image.TARGET_COLOR, dtype=torch.uint8)).all(-1)
    assert blue.any()
    assert (only_target == 255).all(-1).float().mean() > 0.8           # mostly white background
    rope_only = image.render_ropes(ropes[:1], None, size=48)[0]
    assert (rope_only == torch.tensor(image.ROPE_COLOR, dtype=torch.uint8)).all(-1).any()
