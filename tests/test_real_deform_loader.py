"""DEFORM's recordings are read exactly and safely (diffdlo/chain3d/deform.py): files written here in DEFORM's format
(a pickled nested list of shape (T, 3, n)) come back exactly; a pickle that would import or call anything is refused
without running it; malformed files are refused naming the file and the problem."""
import io
import os
import pickle
import random

import pytest
import torch

from diffdlo.chain3d import deform
from diffdlo.chain3d.deform import RecordingError, load_recording, load_split


def deform_list(frames=5, markers=13, seed=0):
    """A nested list (frames, 3, markers) of floats, as DEFORM pickles its recordings."""
    rng = random.Random(seed)
    return [[[rng.uniform(-1.0, 1.0) for _ in range(markers)] for _ in range(3)] for _ in range(frames)]


def write(path, data, protocol=pickle.DEFAULT_PROTOCOL):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=protocol)
    return path


@pytest.mark.parametrize("protocol", [0, 2, pickle.HIGHEST_PROTOCOL])
def test_a_recording_comes_back_exactly_as_frames_markers_xyz(tmp_path, protocol):
    data = deform_list(frames=7, markers=13)
    data[3][2][5] = 2                                   # an int is a number too
    positions = load_recording(write(tmp_path / "0.pkl", data, protocol))
    assert positions.dtype == torch.float64 and positions.shape == (7, 13, 3)
    expected = torch.tensor(data, dtype=torch.float64).transpose(1, 2)
    assert torch.equal(positions, expected)
    assert positions[3, 5, 2].item() == 2.0 and positions[6, 12, 0].item() == data[6][0][12]


def test_tuples_are_accepted_like_lists(tmp_path):
    data = tuple(tuple(tuple(row) for row in frame) for frame in deform_list(frames=3, markers=4))
    assert load_recording(write(tmp_path / "t.pkl", data)).shape == (3, 4, 3)


class RunsACommand:
    """A payload that would run a shell command when unpickled by a plain pickle.load."""
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class AnyClass:
    def __init__(self):
        self.value = 1.0


@pytest.mark.parametrize("protocol", [0, 2, pickle.HIGHEST_PROTOCOL])
def test_a_pickle_that_would_run_a_command_is_refused_and_never_runs(tmp_path, protocol):
    marker = tmp_path / "ran"
    data = deform_list(frames=3, markers=4)
    data[1][0][2] = RunsACommand(marker)                # hidden deep inside an otherwise good recording
    path = write(tmp_path / "evil.pkl", data, protocol)
    with pytest.raises(RecordingError, match="evil.pkl") as err:
        load_recording(path)
    assert "refused opcode" in str(err.value) and "system" in str(err.value)
    assert not marker.exists(), "the payload ran"


def test_the_unpickler_itself_refuses_every_global_even_past_the_opcode_check(tmp_path):
    marker = tmp_path / "ran"
    raw = pickle.dumps([RunsACommand(marker)], protocol=2)
    with pytest.raises(pickle.UnpicklingError, match="refused to load the global .*system"):
        deform.SafeUnpickler(io.BytesIO(raw)).load()
    assert not marker.exists(), "the payload ran"


@pytest.mark.parametrize("payload", [AnyClass(), torch.zeros(2), {1: 2.0}, "1.0", None, b"x", {1.0}, True],
                         ids=["class", "tensor", "dict", "str", "None", "bytes", "set", "bool"])
def test_anything_but_numbers_in_lists_is_refused_naming_the_file(tmp_path, payload):
    data = deform_list(frames=3, markers=4)
    data[2][1][3] = payload
    with pytest.raises(RecordingError, match="bad.pkl"):
        load_recording(write(tmp_path / "bad.pkl", data))


def test_a_whole_file_of_the_wrong_kind_is_refused(tmp_path):
    for name, data in [("dict.pkl", {"positions": deform_list()}), ("str.pkl", "hello"), ("float.pkl", 1.0)]:
        with pytest.raises(RecordingError, match=name) as err:
            load_recording(write(tmp_path / name, data))
        assert "(T, 3, n)" in str(err.value)


@pytest.mark.parametrize("change, problem", [
    (lambda d: d[2][1].pop(), "not rectangular: frame 2, row y has 12 markers, frame 0 has 13"),
    (lambda d: d[1].pop(), "frame 1 has 2 rows, need 3"),
    (lambda d: d[0][2].__setitem__(4, float("nan")), "frame 0, row z, marker 4 is nan, not finite"),
    (lambda d: d[3][0].__setitem__(0, float("-inf")), "frame 3, row x, marker 0 is -inf, not finite"),
    (lambda d: d[1][1].__setitem__(1, 10 ** 400), "not finite"),
    (lambda d: d.__setitem__(slice(1, None), []), "1 frame(s), need at least 2"),
    (lambda d: [row.__delitem__(slice(3, None)) for frame in d for row in frame], "3 marker(s) per frame"),
])
def test_malformed_recordings_are_refused_naming_the_file_and_the_problem(tmp_path, change, problem):
    data = deform_list(frames=5, markers=13)
    change(data)
    with pytest.raises(RecordingError) as err:
        load_recording(write(tmp_path / "broken.pkl", data))
    assert "broken.pkl" in str(err.value) and problem in str(err.value)


@pytest.mark.parametrize("data, problem", [
    ([1.0, 2.0, 3.0], "not rank 1"),
    ([[1.0, 2.0, 3.0]] * 4, "not rank 2"),
    ([[[0.0] * 3] * 13] * 5, "is it (T, n, 3)?"),
])
def test_wrong_rank_is_refused(tmp_path, data, problem):
    with pytest.raises(RecordingError) as err:
        load_recording(write(tmp_path / "rank.pkl", data))
    assert "rank.pkl" in str(err.value) and problem in str(err.value)


def test_unreadable_and_missing_files_are_refused_naming_them(tmp_path):
    (tmp_path / "cut.pkl").write_bytes(pickle.dumps(deform_list())[:50])
    with pytest.raises(RecordingError, match="cut.pkl: not a readable pickle"):
        load_recording(tmp_path / "cut.pkl")
    with pytest.raises(RecordingError, match="nowhere.pkl: no such recording file"):
        load_recording(tmp_path / "nowhere.pkl")


def test_a_split_is_loaded_in_id_order_from_the_data_set_folder_or_the_checkout(tmp_path):
    data_set = tmp_path / "DEFORM" / "data_set"
    written = {i: deform_list(frames=3, markers=12, seed=i) for i in (10, 2, 1)}
    for i, data in written.items():
        write(data_set / "DLO3" / "eval" / f"{i}.pkl", data)
    for root in (data_set, tmp_path / "DEFORM"):
        split = load_split(root, 3, "eval")
        assert list(split) == ["1", "2", "10"]
        for i in written:
            assert torch.equal(split[str(i)], torch.tensor(written[i], dtype=torch.float64).transpose(1, 2))


def test_a_missing_or_empty_split_or_a_wrong_marker_count_is_refused_naming_the_path(tmp_path):
    with pytest.raises(RecordingError, match="nothing_here: no such folder"):
        load_split(tmp_path / "nothing_here", 1, "train")
    with pytest.raises(RecordingError, match=r"DLO1[/\\]train: no such folder"):
        load_split(tmp_path, 1, "train")
    (tmp_path / "DLO1" / "train").mkdir(parents=True)
    with pytest.raises(RecordingError, match=r"DLO1[/\\]train: holds no recordings"):
        load_split(tmp_path, 1, "train")
    write(tmp_path / "DLO1" / "train" / "0.pkl", deform_list(markers=12))
    with pytest.raises(RecordingError, match=r"0.pkl: has 12 markers per frame, but DLO1 carries 13"):
        load_split(tmp_path, 1, "train")
    with pytest.raises(RecordingError, match="cable must be one of"):
        load_split(tmp_path, 6, "train")
    with pytest.raises(RecordingError, match="split must be one of"):
        load_split(tmp_path, 1, "test")


def test_the_cable_table_and_constants():
    assert deform.DT == 0.01 and deform.HELD_MARKERS == (0, 1, -2, -1)
    assert [c.length for c in deform.CABLES.values()] == [1.152, 0.996, 0.998, 0.973, 0.988]
    assert [round(c.mass * 1e3, 1) for c in deform.CABLES.values()] == [34.5, 65.2, 96.8, 22.0, 19.2]
    ranks = [c.stiffness_rank for c in deform.CABLES.values()]
    assert ranks == [3, 4, 5, 1, 2] and max(deform.CABLES.values(), key=lambda c: c.stiffness_rank).name == "DLO3"
    assert deform.CABLES[1].n_markers == 13 and {deform.CABLES[i].n_markers for i in (2, 3, 4, 5)} == {12}
    assert deform.MARKER_DIAMETER == pytest.approx(7.9e-3) and deform.MARKER_MASS == pytest.approx(0.4e-3)
    assert deform.CABLES[1].mass_per_length == pytest.approx(34.5e-3 / 1.152)
