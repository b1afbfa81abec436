"""The recording format (diffdlo/calibration/recording.py) and the simulator-made recording (python -m diffdlo.calibration.record): exact
round trips, frames that are the simulator's moves, noise and dropout as asked, every malformed file refused naming
its field, and the command line's guards."""
import dataclasses
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

import diffdlo
from diffdlo.calibration import record
from diffdlo.planar.params import PARAMS_DIR
from diffdlo.calibration.recording import Recording, RecordingError, load_recording, recording_arrays, save_recording

RECORD_EVERY = 10


@pytest.fixture(scope="module")
def tiny():
    """6 nodes, 0.15 m, fast drags and a short settle: a move costs about a millisecond."""
    return dataclasses.replace(diffdlo.load_params(), n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30)


@pytest.fixture(scope="module")
def clean(tiny):
    return record.make_recording(tiny, n_moves=4, seed=3, record_every=RECORD_EVERY)


@pytest.fixture(scope="module")
def clean_file(clean, tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "clean.npz"
    save_recording(path, clean)
    return path


def assert_same(a: Recording, b: Recording) -> None:
    for f in dataclasses.fields(Recording):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "meta":
            assert x == y
        else:
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            torch.testing.assert_close(x, y, rtol=0, atol=0, equal_nan=True, msg=f.name)


# ====================================================================== format
def test_round_trip_is_exact(clean, clean_file, tiny, tmp_path):
    assert_same(load_recording(clean_file, tiny), clean)
    lossy = record.make_recording(tiny, n_moves=2, seed=1, noise=0.002, dropout=0.2, record_every=RECORD_EVERY)
    save_recording(tmp_path / "lossy.npz", lossy)
    assert_same(load_recording(tmp_path / "lossy.npz"), lossy)
    assert [p.name for p in tmp_path.iterdir()] == ["lossy.npz"]          # no temporary file left behind


def test_a_file_without_visible_is_all_visible(clean, tmp_path):
    arrays = recording_arrays(clean)
    del arrays["visible"]
    np.savez(tmp_path / "r.npz", **arrays)
    assert load_recording(tmp_path / "r.npz").visible.all()


def test_frames_are_the_simulators_moves(clean, tiny):
    """Without noise each move's end frame is sim.move of its start frame, node and drag: exactly on the default
    (kernel) path that records, to rounding on the eager path; moves chain and times follow the substeps."""
    rec = clean
    assert rec.n_moves == 4 and rec.n_nodes == 6 and rec.visible.all()
    assert (rec.move_start[1:] == rec.move_end[:-1]).all() and rec.move_start[0] == 0
    assert rec.move_end[-1] == rec.n_frames - 1
    eager = diffdlo.Simulator(tiny, dtype=torch.float64, backend="torch")
    default = diffdlo.Simulator(tiny, dtype=torch.float64)
    for m in range(rec.n_moves):
        start, end = int(rec.move_start[m]), int(rec.move_end[m])
        args = (rec.positions[start][None], rec.move_node[m:m + 1], rec.move_delta[m:m + 1])
        new, info = default.move(*args, return_info=True)
        assert torch.equal(new[0], rec.positions[end])
        torch.testing.assert_close(eager.move(*args)[0], rec.positions[end], rtol=0, atol=1e-10)
        elapsed = (rec.times[end] - rec.times[start]).item()
        assert elapsed == pytest.approx(int(info.substeps[0]) * tiny.dt, abs=1e-12)
        assert end - start == len(record.frame_substeps(int(info.substeps[0]), RECORD_EVERY)) - 1
    assert (rec.move_delta.norm(dim=-1) <= tiny.max_disp + 1e-12).all()
    assert (rec.move_delta.abs() <= tiny.action_scale).all()
    assert rec.meta["source"] == "simulator" and rec.meta["true_params"]["k_s"] == tiny.k_s


def test_frame_substeps_drop_the_duplicated_end():
    assert record.frame_substeps(25, 10) == [0, 10, 20, 25]
    assert record.frame_substeps(30, 10) == [0, 10, 20, 30]


def test_noise_has_the_asked_std_and_leaves_the_moves(tiny):
    clean = record.make_recording(tiny, n_moves=6, seed=3, record_every=2)
    noisy = record.make_recording(tiny, n_moves=6, seed=3, noise=0.01, record_every=2)
    err = noisy.positions - clean.positions
    assert err.numel() > 3000
    assert err.std().item() == pytest.approx(0.01, rel=0.1)
    assert abs(err.mean().item()) < 0.002
    assert torch.equal(noisy.move_delta, clean.move_delta) and torch.equal(noisy.times, clean.times)


def test_dropout_marks_nodes_lost(clean, tiny):
    lossy = record.make_recording(tiny, n_moves=4, seed=3, dropout=0.3, record_every=RECORD_EVERY)
    lost = ~lossy.visible
    assert 0.2 < lost.float().mean().item() < 0.4
    assert torch.isnan(lossy.positions[lost]).all()
    assert torch.equal(lossy.positions[~lost], clean.positions[~lost])   # noise 0: the rest untouched


def test_scale_changes_the_true_rope(tiny):
    rec = record.make_recording(tiny, n_moves=1, seed=0, record_every=RECORD_EVERY, scale={"k_d": 0.5, "mass": 2})
    assert rec.meta["true_params"] == {"k_s": tiny.k_s, "k_b": tiny.k_b, "k_d": tiny.k_d * 0.5, "mass": tiny.mass * 2}
    true = record.scaled_params(tiny, {"k_d": 0.5, "mass": 2})
    sim = diffdlo.Simulator(true, dtype=torch.float64)
    end = sim.move(rec.positions[0][None], rec.move_node[:1], rec.move_delta[:1])[0]
    assert torch.equal(end, rec.positions[int(rec.move_end[0])])
    with pytest.raises(ValueError, match="k_f"):
        record.scaled_params(tiny, {"k_f": 2.0})
    with pytest.raises(ValueError, match="positive"):
        record.scaled_params(tiny, {"k_s": 0.0})


def test_save_refuses_a_bad_recording(clean, tmp_path):
    bad = dataclasses.replace(clean, times=clean.times.flip(0))
    with pytest.raises(RecordingError, match="'times'"):
        save_recording(tmp_path / "bad.npz", bad)
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------- corrupted files
def _set(key, value):
    return lambda a: a.update({key: value(a) if callable(value) else value})


def _drop(key):
    return lambda a: a.pop(key)


def _edit(key, fn):
    def apply(a):
        x = a[key].copy()
        fn(x)
        a[key] = x
    return apply


def _hide_but_keep(a):
    a["visible"] = a["visible"].copy()
    a["visible"][2, 1] = False


CORRUPTIONS = {
    "missing positions": (_drop("positions"), "positions"),
    "missing times": (_drop("times"), "times"),
    "missing move_end": (_drop("move_end"), "move_end"),
    "missing meta": (_drop("meta"), "meta"),
    "unknown key": (_set("visable", np.ones(3)), "visable"),
    "positions 2-d": (_set("positions", lambda a: a["positions"][..., 0]), "'positions' must have shape (T, N, 2)"),
    "positions 3-d coords": (_set("positions", lambda a: np.zeros(a["positions"].shape[:2] + (3,))), "'positions'"),
    "positions integers": (_set("positions", lambda a: a["positions"].astype(np.int64)),
                           "'positions' must hold floats"),
    "positions nan where visible": (_edit("positions", lambda x: x.__setitem__((5, 2, 0), np.nan)),
                                    "'positions' must be finite where visible"),
    "positions inf where visible": (_edit("positions", lambda x: x.__setitem__((0, 0, 1), np.inf)), "'positions'"),
    "positions where not visible": (_hide_but_keep, "'positions' must be NaN where not visible"),
    "times too long": (_set("times", lambda a: np.append(a["times"], 99.0)), "'times' must have shape (T,)"),
    "times 2-d": (_set("times", lambda a: a["times"][:, None]), "'times' must have shape"),
    "times repeated": (_edit("times", lambda x: x.__setitem__(3, x[2])), "'times' must be strictly increasing"),
    "times backwards": (_edit("times", lambda x: x.__setitem__(slice(None), x[::-1].copy())),
                        "'times' must be strictly increasing"),
    "times nan": (_edit("times", lambda x: x.__setitem__(4, np.nan)), "'times' must be finite"),
    "visible shape": (_set("visible", lambda a: a["visible"][:-1]), "'visible' must have shape (T, N)"),
    "visible not bool": (_set("visible", lambda a: a["visible"].astype(np.int8)), "'visible' must hold booleans"),
    "move_node out of range": (_edit("move_node", lambda x: x.__setitem__(1, 6)), "'move_node' must be a node id"),
    "move_node negative": (_edit("move_node", lambda x: x.__setitem__(0, -1)), "'move_node' must be a node id"),
    "move_node floats": (_set("move_node", lambda a: a["move_node"].astype(float)), "'move_node' must hold integers"),
    "move_node 2-d": (_set("move_node", lambda a: a["move_node"][:, None]), "'move_node' must have shape (M,)"),
    "move_delta nan": (_edit("move_delta", lambda x: x.__setitem__((2, 1), np.nan)), "'move_delta' must be finite"),
    "move_delta shape": (_set("move_delta", lambda a: a["move_delta"][:-1]), "'move_delta' must have shape (M, 2)"),
    "move_start shape": (_set("move_start", lambda a: a["move_start"][:-1]), "'move_start' must have shape (M,)"),
    "move_end past the last frame": (_edit("move_end", lambda x: x.__setitem__(-1, 10_000)),
                                     "'move_end' must be a frame index"),
    "move_start negative": (_edit("move_start", lambda x: x.__setitem__(0, -1)), "'move_start' must be a frame index"),
    "move ends before it starts": (_edit("move_end", lambda x: x.__setitem__(0, 0)), "'move_start' must be before"),
    "moves overlap": (_edit("move_start", lambda x: x.__setitem__(2, x[2] - 1)), "'move_start' must not fall before"),
    "moves out of time order": (lambda a: [a.update({k: a[k][::-1].copy()}) for k in
                                           ("move_node", "move_delta", "move_start", "move_end")],
                                "'move_start' must not fall before"),
    "meta not json": (_set("meta", np.array("{source: simulator")), "'meta' is not valid JSON"),
    "meta not an object": (_set("meta", np.array("[1, 2]")), "'meta' must be a JSON object"),
    "meta bad source": (_set("meta", np.array(json.dumps({"source": "camera"}))), "'meta' must have 'source'"),
    "meta not a string": (_set("meta", np.zeros(2)), "'meta' must be a JSON string"),
    "meta pickled": (_set("meta", np.array({"source": "simulator"}, dtype=object)), "'meta' cannot be read"),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_a_corrupted_file_is_refused_naming_its_field(name, clean, tiny, tmp_path):
    corrupt, message = CORRUPTIONS[name]
    arrays = recording_arrays(clean)
    corrupt(arrays)
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(RecordingError, match=re.escape(f"{path}: ") + ".*" + re.escape(message)):
        load_recording(path, tiny)


def test_the_node_count_is_checked_against_the_params(clean_file, tiny):
    with pytest.raises(RecordingError, match=r"'positions' has 6 nodes per frame but .* n_nodes=20"):
        load_recording(clean_file, diffdlo.load_params())
    assert load_recording(clean_file).n_nodes == tiny.n_nodes                # no params: any node count


@pytest.mark.parametrize("content", ["text", "npy", "missing"])
def test_a_file_that_is_not_an_npz_is_refused(content, tmp_path):
    path = tmp_path / "r.npz"
    if content == "text":
        path.write_text("frame,node,x,y\n0,0,0.1,0.2\n")
    elif content == "npy":
        with open(path, "wb") as f:
            np.save(f, np.zeros((3, 6, 2)))
    with pytest.raises(RecordingError, match="no such recording file" if content == "missing" else "not an .npz"):
        load_recording(path)


# ====================================================================== command line
@pytest.fixture(scope="module")
def tiny_yaml(tiny, tmp_path_factory):
    raw = yaml.safe_load((PARAMS_DIR / "cable.yaml").read_text())
    raw["model"].update(n_nodes=tiny.n_nodes, length=tiny.length)
    raw["controller"]["max_speed"] = tiny.max_speed
    raw["settle"]["max_substeps"] = tiny.settle_max_substeps
    path = tmp_path_factory.mktemp("params") / "tiny.yaml"
    path.write_text(yaml.safe_dump(raw))
    return str(path)


def test_cli_writes_a_recording_and_refuses_to_overwrite(tiny_yaml, tiny, tmp_path, capsys):
    out = tmp_path / "sub" / "rec.npz"
    flags = ["--out", str(out), "--params", tiny_yaml, "--moves", "2", "--record-every", "5", "--noise", "0",
             "--dropout", "0.1", "--scale", "k_s=1.3", "--scale", "k_d=0.8", "--seed", "7"]
    assert record.main(flags) == 0
    summary = capsys.readouterr().out
    assert "frames" in summary and "2 moves" in summary and "k_s=1298.7" in summary and "k_d=80" in summary
    rec = load_recording(out, tiny)
    assert rec.n_moves == 2 and not rec.visible.all()
    assert rec.meta["seed"] == 7 and rec.meta["scale"] == {"k_s": 1.3, "k_d": 0.8} and rec.meta["params"] == tiny_yaml
    before = out.read_bytes()

    assert record.main(flags[:-2] + ["--seed", "8"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already exists" in err and str(out) in err
    assert out.read_bytes() == before
    assert record.main(flags + ["--overwrite"]) == 0
    assert load_recording(out, tiny).n_moves == 2


BAD_FLAGS = [
    (["--moves", "0"], "'0'"),
    (["--moves", "two"], "'two'"),
    (["--seed", "-1"], "'-1'"),
    (["--noise", "-0.1"], "'-0.1'"),
    (["--noise", "nan"], "'nan'"),
    (["--dropout", "1"], "'1'"),
    (["--record-every", "0"], "'0'"),
    (["--scale", "k_f=2"], "'k_f'"),
    (["--scale", "k_s=-1"], "'-1'"),
    (["--scale", "k_s=inf"], "'inf'"),
    (["--scale", "k_s"], "'k_s'"),
    (["--scale", "k_s=2", "--scale", "k_s=3"], "k_s given twice"),
    (["--params", "no_such_params"], "no_such_params"),
    (["--out", "rec.txt"], "'rec.txt'"),
    (["--bogus"], "--bogus"),
]


@pytest.mark.parametrize("flags,named", BAD_FLAGS, ids=[" ".join(f) for f, _ in BAD_FLAGS])
def test_cli_rejects_bad_flags_in_one_line(flags, named, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["--out", str(tmp_path / "r.npz"), "--moves", "1"] + flags
    assert record.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("python -m diffdlo.calibration.record: error:") and named in err
    assert not list(tmp_path.iterdir())


def test_the_module_runs_and_exits_2_on_a_bad_flag(tmp_path):
    result = subprocess.run([sys.executable, "-m", "diffdlo.calibration.record", "--out", str(tmp_path / "r.npz"), "--noise",
                             "-1"], capture_output=True, text=True, timeout=60,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "'-1'" in result.stderr, result.stderr
