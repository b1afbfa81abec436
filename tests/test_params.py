"""load_params: the defaults load, and every bad file or value gives an error naming the field and the value."""
import dataclasses
from pathlib import Path

import pytest
import yaml

import diffdlo
from diffdlo.planar.params import _RANGES, PARAMS_DIR, CableParams, ParamsError


def test_defaults_match_table_2_1(params):
    assert (params.n_nodes, params.length, params.mass) == (20, 0.5, 0.2)
    assert (params.k_s, params.k_b, params.k_d, params.dt) == (999.0, 0.01, 100.0, 0.001)
    assert params.node_mass == pytest.approx(0.01) and params.rest_length == pytest.approx(0.5 / 19)
    assert params.controller == "kinematic"
    assert dataclasses.replace(params, k_d=0.0).k_d == 0.0
    assert diffdlo.load_params(PARAMS_DIR / "cable.yaml") == params


def write_variant(tmp_path: Path, section: str, key: str, value=None, drop=False) -> Path:
    raw = yaml.safe_load(open(PARAMS_DIR / "cable.yaml"))
    if drop:
        del raw[section][key]
    else:
        raw[section][key] = value
    path = tmp_path / "variant.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("section,key,value,message", [
    ("model", "k_s", None, r"missing field 'model\.k_s'"),
    ("settle", "threshold", None, r"missing field 'settle\.threshold'"),
    ("model", "k_s", "stiff", r"'k_s' must be a number, got 'stiff' \(str\)"),
    ("model", "n_nodes", 20.5, r"'n_nodes' must be an integer, got 20\.5"),
    ("model", "k_b", -0.01, r"'k_b' must be >= 0 .*got -0\.01"),
    ("model", "k_s", -5.0, r"'k_s' must be > 0 .*got -5\.0"),
    ("model", "mass", -0.2, r"'mass' must be > 0, got -0\.2"),
    ("model", "mass", 0, r"'mass' must be > 0, got 0"),
    ("model", "n_nodes", 2, r"'n_nodes' must be >= 3 \(bending needs an interior node\), got 2"),
    ("model", "dt", 0.05, r"'dt' = 0\.05 makes the integrator unstable"),
    ("controller", "type", "magic", r"'controller' must be one of \('kinematic', 'pid'\), got 'magic'"),
    ("env", "workspace", [2.0], r"'workspace' must be \[width, height\], got \(2\.0,\)"),
    ("model", "k_d", float("nan"), r"'k_d' must be finite, got nan"),
    ("model", "k_s", True, r"'k_s' must be a number, got True"),
])
def test_bad_files_name_the_field_and_value(tmp_path, section, key, value, message):
    path = write_variant(tmp_path, section, key, value, drop=value is None)
    with pytest.raises(ParamsError, match=message):
        diffdlo.load_params(path)


def test_unknown_fields_files_and_overrides(tmp_path):
    path = write_variant(tmp_path, "model", "k_twist", 1.0)
    with pytest.raises(ParamsError, match=r"unknown field\(s\) in section 'model': \['k_twist'\]"):
        diffdlo.load_params(path)
    with pytest.raises(ParamsError, match="no cable parameter file 'nope'"):
        diffdlo.load_params("nope")
    with pytest.raises(ParamsError, match=r"unknown cable parameter override\(s\) \['stiffness'\]"):
        diffdlo.load_params("cable", stiffness=3)
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: [1, 2\n")
    with pytest.raises(ParamsError, match="not valid YAML"):
        diffdlo.load_params(bad)


@pytest.mark.parametrize("section,key,value", [("model", "k_f", 0.05), ("controller", "ff_dt", 0.0005)])
def test_removed_fields_are_rejected_with_the_reason(tmp_path, params, section, key, value):
    """k_f and ff_dt drove nothing: an old file that still sets one fails and says so instead of being ignored."""
    assert not hasattr(params, key)
    path = write_variant(tmp_path, section, key, value)
    with pytest.raises(ParamsError, match=rf"field '{section}\.{key}' was removed because it did nothing .*"
                                          rf"delete it from the file"):
        diffdlo.load_params(path)
    with pytest.raises(ParamsError, match=rf"cable parameter '{key}' was removed because it did nothing"):
        diffdlo.load_params("cable", **{key: value})
    with pytest.raises(TypeError, match=key):
        dataclasses.replace(params, **{key: value})


def test_replace_validates_too(params):
    with pytest.raises(ParamsError, match=r"'k_s' must be > 0 .*got -1\.0"):
        dataclasses.replace(params, k_s=-1.0)
    with pytest.raises(ParamsError, match="unstable"):
        dataclasses.replace(params, k_d=0.0, dt=0.01)
    assert diffdlo.load_params("cable", k_d=0.0).k_d == 0.0


@pytest.mark.parametrize("field,value,allowed", [
    ("k_s", 0.0, "> 0"), ("k_s", -1.0, "> 0"), ("k_b", -0.5, ">= 0"), ("k_d", -1.0, ">= 0"),
    ("mass", 0.0, "> 0"), ("mass", -0.1, "> 0"), ("dt", 0.0, "> 0"), ("dt", -0.001, "> 0"),
    ("n_nodes", 2, ">= 3"), ("n_nodes", 0, ">= 3"), ("length", 0.0, "> 0"), ("length", -0.5, "> 0"),
    ("settle_check_every", 0, ">= 1"), ("max_episode_steps", 0, ">= 1"), ("max_drag_steps", -3, ">= 1"),
    ("k_s", float("inf"), "finite"), ("k_b", float("nan"), "finite"), ("mass", float("-inf"), "finite"),
    ("dt", float("nan"), "finite"), ("length", float("inf"), "finite"),
    ("n_nodes", 20.0, "an integer"), ("k_s", "999", "a number"), ("k_d", None, "a number"),
    ("workspace", (0.0, 2.0), "> 0"),
])
def test_bad_override_names_the_field_the_value_and_the_range(field, value, allowed):
    """Overrides go through the same checks as files: the message says which field, what value, what is allowed."""
    with pytest.raises(ParamsError) as err:
        diffdlo.load_params("cable", **{field: value})
    message = str(err.value)
    assert f"'{field}'" in message and repr(value) in message and allowed in message, message


def test_boundary_values_are_accepted(params):
    """0 is a valid k_b (a chain) and k_d (undamped); 3 nodes are the fewest that can bend."""
    assert diffdlo.load_params("cable", k_b=0.0, k_d=0.0).k_b == 0.0
    assert diffdlo.load_params("cable", n_nodes=3).rest_length == pytest.approx(params.length / 2)


def test_every_numeric_field_has_a_range():
    """A new field cannot skip validation: each number of CableParams has an allowed range."""
    numeric = {f.name for f in dataclasses.fields(CableParams)} - {"controller", "workspace"}
    assert set(_RANGES) == numeric
