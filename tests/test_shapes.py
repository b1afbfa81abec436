"""Target shapes: named, arrays, .npy and .yaml files, and clear errors for bad ones."""
import math

import numpy as np
import pytest
import torch
import yaml

import diffdlo
from diffdlo import TargetError


@pytest.mark.parametrize("name,angle", [("horizontal", 0), ("vertical", 90), ("diagonal", 45),
                                        ("antidiagonal", 135)])
def test_named_targets_are_full_length_lines_from_node_0(params, name, angle):
    t = diffdlo.target_shape(name, params, dtype=torch.float64)
    assert t.shape == (params.n_nodes, 2)
    torch.testing.assert_close(t.mean(0), torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-12)
    direction = t[-1] - t[0]
    assert direction.norm().item() == pytest.approx(params.length)
    assert math.degrees(math.atan2(direction[1], direction[0])) == pytest.approx(angle)


def arc(params, radius=0.25):
    phi = params.rest_length / radius
    k = np.arange(params.n_nodes)
    # chord length 2 r sin(phi/2) differs from the rest length by < 0.1%
    return np.stack([radius * np.cos(k * phi), radius * np.sin(k * phi)], axis=1)


def test_custom_arrays_npy_and_yaml_files(params, tmp_path):
    points = arc(params)
    from_array = diffdlo.target_shape(points, params, dtype=torch.float64)
    torch.testing.assert_close(from_array, torch.as_tensor(points))
    np.save(tmp_path / "arc.npy", points)
    torch.testing.assert_close(diffdlo.target_shape(tmp_path / "arc.npy", params, dtype=torch.float64), from_array)
    (tmp_path / "arc.yaml").write_text(yaml.safe_dump({"points": points.tolist()}))
    torch.testing.assert_close(diffdlo.target_shape(str(tmp_path / "arc.yaml"), params, dtype=torch.float64),
                               from_array)
    (tmp_path / "list.yml").write_text(yaml.safe_dump(points.tolist()))
    torch.testing.assert_close(diffdlo.target_shape(tmp_path / "list.yml", params, dtype=torch.float64), from_array)


def test_bad_targets_give_clear_errors(params, tmp_path):
    with pytest.raises(TargetError, match=r"unknown target 'zigzag'"):
        diffdlo.target_shape("zigzag", params)
    with pytest.raises(TargetError, match=r"must have shape \(20, 2\).*got \(19, 2\)"):
        diffdlo.target_shape(arc(params)[:19], params)
    stretched = arc(params) * 1.5
    with pytest.raises(TargetError, match=r"link \d+ \(nodes \d+-\d+\) is 0\.0395 m long.*0\.0263 m"):
        diffdlo.target_shape(stretched, params)
    with pytest.raises(TargetError, match="does not exist"):
        diffdlo.target_shape(tmp_path / "missing.npy", params)
    nan = arc(params)
    nan[3, 1] = np.nan
    with pytest.raises(TargetError, match=r"NaN or inf: node 3 is \[.*, nan\]"):
        diffdlo.target_shape(nan, params)
    coincident = arc(params)
    coincident[8] = coincident[7]
    with pytest.raises(TargetError, match="nodes 7 and 8 are 0 m apart"):
        diffdlo.target_shape(coincident, params)
    (tmp_path / "words.yaml").write_text("points: [[a, b]]\n")
    with pytest.raises(TargetError, match="not an \\(N, 2\\) array of numbers"):
        diffdlo.target_shape(tmp_path / "words.yaml", params)
    (tmp_path / "keys.yaml").write_text("nodes: []\n")
    with pytest.raises(TargetError, match="key 'points'"):
        diffdlo.target_shape(tmp_path / "keys.yaml", params)
