import torch

import diffdlo
from diffdlo.tasks import image


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


def _dense_coverage(polylines, size, view_size, width):
    """Brute force: every pixel against every segment (the definition)."""
    px = view_size / size
    grid = image.pixel_centres(size, view_size, dtype=polylines.dtype).view(-1, 2)
    a, b = polylines[:, :-1], polylines[:, 1:]
    ap = grid[None, :, None, :] - a[:, None]
    ab = (b - a)[:, None]
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0, 1)
    d = (ap - t[..., None] * ab).norm(dim=-1).amin(-1)
    return (0.5 + (width / 2 - d) / px).clamp(0, 1).view(-1, size, size)


def test_windowed_coverage_equals_the_dense_definition():
    import diffdlo
    p = diffdlo.load_params()
    ropes = diffdlo.random_shape(5, p, torch.Generator().manual_seed(0), dtype=torch.float64)
    ropes = ropes * 1.3 + torch.tensor([0.12, -0.05], dtype=torch.float64)   # partly outside the small views
    for size, view in [(64, 1.0), (200, 1.0), (32, 2.0), (48, 0.3)]:
        width = max(2.0 * view / size, 0.015 * view)
        fast = image.coverage(ropes, size, view)
        assert fast.max() == 1.0 and fast.min() == 0.0
        torch.testing.assert_close(fast, _dense_coverage(ropes, size, view, width), rtol=0, atol=1e-9)
