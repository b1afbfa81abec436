"""Recordings of a cable being moved: the data a calibration of the physical parameters fits the simulator to.

Format
------
A recording is one ``.npz`` file (``numpy.savez``, no pickled objects) holding these arrays. T is the number of
frames, N the number of rope nodes, M the number of recorded moves.

=============  ==========  =====  ==================================================================================
key            shape       dtype  meaning
=============  ==========  =====  ==================================================================================
``positions``  (T, N, 2)   float  node positions [m] in the table's plane, per frame; NaN where ``visible`` is False
``times``      (T,)        float  time of each frame [s], finite and strictly increasing
``move_node``  (M,)        int    the node grasped by move m, in [0, N)
``move_delta`` (M, 2)      float  the drag of move m [m]: the grasped node's displacement, finite
``move_start`` (M,)        int    index of the frame where move m starts (the rope at rest just before the grasp)
``move_end``   (M,)        int    index of the frame where move m's settle ends (the rope released and left to rest)
``visible``    (T, N)      bool   optional: False where tracking lost a node in a frame (absent: every node seen)
``meta``       ()          str    a JSON object; ``source`` is required, the other keys are documented below
=============  ==========  =====  ==================================================================================

Moves are in time order and do not overlap: ``0 <= move_start[m] < move_end[m] < T`` and
``move_end[m] <= move_start[m + 1]``. A move's end frame may be the next move's start frame (the simulator's
recordings do this: the next grasp starts from where the last settle left the rope). Positions must be finite
where visible and NaN where not. No other keys are allowed, so a misspelled one is caught.

``meta`` keys: ``source`` ("simulator" or "real", required); ``params`` (the name or path of the cable parameters
the recording was made with, or is meant to be replayed with), ``dt`` (their integrator substep [s]), ``noise``
(std of the position noise [m]), ``seed`` (int or null); a simulator-made recording (``python -m diffdlo.calibration.record``)
also has ``record_every`` (substeps between frames), ``dropout`` (chance a node is dropped from a frame),
``scale`` (the factors applied to the named parameters) and ``true_params`` (k_s, k_b, k_d, mass it was made with).

``load_recording`` checks all of the above (and the node count against given parameters) and raises
``RecordingError`` naming the field and the problem; ``save_recording`` runs the same checks before it writes, and
writes atomically (a reader sees the old file or the new one, never half of one).
"""
from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..utils.files import replacing
from ..planar.params import CableParams

SOURCES = ("simulator", "real")
REQUIRED_KEYS = ("positions", "times", "move_node", "move_delta", "move_start", "move_end", "meta")
OPTIONAL_KEYS = ("visible",)


class RecordingError(ValueError):
    """A recording file or value is invalid; the message names the field and the problem."""


@dataclasses.dataclass(frozen=True)
class Recording:
    """One recording as CPU tensors: float64 positions and times, int64 move indices, a bool visibility mask
    (all True when the file has none) and the meta dict. See the module docstring for the meaning of each field."""

    positions: torch.Tensor     # (T, N, 2) float64 [m], NaN where not visible
    times: torch.Tensor         # (T,) float64 [s]
    move_node: torch.Tensor     # (M,) int64
    move_delta: torch.Tensor    # (M, 2) float64 [m]
    move_start: torch.Tensor    # (M,) int64 frame index
    move_end: torch.Tensor      # (M,) int64 frame index
    visible: torch.Tensor       # (T, N) bool
    meta: dict[str, Any]

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_nodes(self) -> int:
        return self.positions.shape[1]

    @property
    def n_moves(self) -> int:
        return self.move_node.shape[0]

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return float(self.times[-1] - self.times[0])


# ====================================================================== checks, on numpy arrays
def _fail(where: str, field: str, problem: str) -> RecordingError:
    return RecordingError(f"{where}: field {field!r} {problem}")


def _check_kind(where: str, field: str, a: np.ndarray, kinds: str, want: str) -> None:
    if a.dtype.kind not in kinds:
        raise _fail(where, field, f"must hold {want}, got dtype {a.dtype}")


def _check_shape(where: str, field: str, a: np.ndarray, shape: tuple[int | None, ...], text: str) -> None:
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape))
    if not ok:
        raise _fail(where, field, f"must have shape {text}, got {a.shape}")


def _parse_meta(where: str, raw: np.ndarray) -> dict[str, Any]:
    if raw.shape != () or raw.dtype.kind != "U":
        raise _fail(where, "meta", f"must be a JSON string (a 0-d str array), got dtype {raw.dtype} shape {raw.shape}")
    try:
        meta = json.loads(str(raw))
    except ValueError as exc:
        raise _fail(where, "meta", f"is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise _fail(where, "meta", f"must be a JSON object, got {type(meta).__name__}")
    if meta.get("source") not in SOURCES:
        raise _fail(where, "meta", f"must have 'source' one of {SOURCES}, got {meta.get('source')!r}")
    return meta


def _check_arrays(where: str, a: dict[str, np.ndarray], params: CableParams | None) -> None:
    """Every rule of the format on raw arrays (``visible`` already filled in); raises RecordingError."""
    pos, times, visible = a["positions"], a["times"], a["visible"]
    _check_kind(where, "positions", pos, "f", "floats")
    _check_shape(where, "positions", pos, (None, None, 2), "(T, N, 2)")
    n_frames, n_nodes = pos.shape[:2]
    if n_frames < 1 or n_nodes < 1:
        raise _fail(where, "positions", f"must hold at least one frame and one node, got shape {pos.shape}")
    if params is not None and n_nodes != params.n_nodes:
        raise _fail(where, "positions", f"has {n_nodes} nodes per frame but the cable parameters have "
                                        f"n_nodes={params.n_nodes}")
    _check_kind(where, "times", times, "f", "floats")
    _check_shape(where, "times", times, (n_frames,), f"(T,) = ({n_frames},), T from positions")
    if not np.isfinite(times).all():
        raise _fail(where, "times", f"must be finite, got {float(times[~np.isfinite(times)][0])} at frame "
                                    f"{int(np.flatnonzero(~np.isfinite(times))[0])}")
    steps = np.diff(times)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0])
        raise _fail(where, "times", f"must be strictly increasing, got {float(times[i])!r} at frame {i} then "
                                    f"{float(times[i + 1])!r} at frame {i + 1}")
    _check_kind(where, "visible", visible, "b", "booleans")
    _check_shape(where, "visible", visible, (n_frames, n_nodes), f"(T, N) = ({n_frames}, {n_nodes})")
    finite = np.isfinite(pos).all(-1)
    bad = visible & ~finite
    if bad.any():
        frame, node = (int(x) for x in np.argwhere(bad)[0])
        raise _fail(where, "positions", f"must be finite where visible, got {pos[frame, node].tolist()} at frame "
                                        f"{frame}, node {node}")
    hidden_not_nan = ~visible & ~np.isnan(pos).all(-1)
    if hidden_not_nan.any():
        frame, node = (int(x) for x in np.argwhere(hidden_not_nan)[0])
        raise _fail(where, "positions", f"must be NaN where not visible, got {pos[frame, node].tolist()} at frame "
                                        f"{frame}, node {node}")
    _check_moves(where, a, n_frames, n_nodes)


def _check_moves(where: str, a: dict[str, np.ndarray], n_frames: int, n_nodes: int) -> None:
    node, delta, start, end = a["move_node"], a["move_delta"], a["move_start"], a["move_end"]
    _check_kind(where, "move_node", node, "iu", "integers")
    _check_shape(where, "move_node", node, (None,), "(M,)")
    n_moves = node.shape[0]
    _check_kind(where, "move_delta", delta, "f", "floats")
    _check_shape(where, "move_delta", delta, (n_moves, 2), f"(M, 2) = ({n_moves}, 2), M from move_node")
    for field, index in (("move_start", start), ("move_end", end)):
        _check_kind(where, field, index, "iu", "integers")
        _check_shape(where, field, index, (n_moves,), f"(M,) = ({n_moves},), M from move_node")
    out = (node < 0) | (node >= n_nodes)
    if out.any():
        m = int(np.flatnonzero(out)[0])
        raise _fail(where, "move_node", f"must be a node id in [0, {n_nodes}), got {int(node[m])} for move {m}")
    finite = np.isfinite(delta).all(-1)
    if not finite.all():
        m = int(np.flatnonzero(~finite)[0])
        raise _fail(where, "move_delta", f"must be finite, got {delta[m].tolist()} for move {m}")
    for field, index in (("move_start", start), ("move_end", end)):
        out = (index < 0) | (index >= n_frames)
        if out.any():
            m = int(np.flatnonzero(out)[0])
            raise _fail(where, field, f"must be a frame index in [0, {n_frames}), got {int(index[m])} for move {m}")
    backwards = start >= end
    if backwards.any():
        m = int(np.flatnonzero(backwards)[0])
        raise _fail(where, "move_start", f"must be before move_end, got start {int(start[m])} >= end "
                                         f"{int(end[m])} for move {m}")
    overlap = start[1:] < end[:-1]
    if overlap.any():
        m = int(np.flatnonzero(overlap)[0]) + 1
        raise _fail(where, "move_start", f"must not fall before the previous move's end (moves in time order, not "
                                         f"overlapping), got start {int(start[m])} for move {m} but move {m - 1} "
                                         f"ends at frame {int(end[m - 1])}")


# ====================================================================== file <-> Recording
def _read_npz(path: Path) -> dict[str, np.ndarray]:
    where = str(path)
    if not path.is_file():
        raise RecordingError(f"{where}: no such recording file")
    if not zipfile.is_zipfile(path):
        raise RecordingError(f"{where}: not an .npz file (numpy.savez archive)")
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise RecordingError(f"{where}: not a readable .npz file: {exc}") from None
    with archive:
        keys = set(archive.files)
        missing = [k for k in REQUIRED_KEYS if k not in keys]
        if missing:
            raise RecordingError(f"{where}: missing field(s) {missing} (a recording has {list(REQUIRED_KEYS)}"
                                 f" and optionally {list(OPTIONAL_KEYS)})")
        unknown = sorted(keys - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
        if unknown:
            raise RecordingError(f"{where}: unknown field(s) {unknown} (a recording has {list(REQUIRED_KEYS)} "
                                 f"and optionally {list(OPTIONAL_KEYS)})")
        arrays = {}
        for key in sorted(keys):
            try:
                arrays[key] = archive[key]
            except (OSError, ValueError, zipfile.BadZipFile) as exc:
                raise _fail(where, key, f"cannot be read: {exc}") from None
    return arrays


def load_recording(path: Path | str, params: CableParams | None = None) -> Recording:
    """Read and check a recording (module docstring); with ``params`` its node count must be ``params.n_nodes``.
    Raises RecordingError naming the file, the field and the problem."""
    path = Path(path)
    where = str(path)
    arrays = _read_npz(path)
    meta = _parse_meta(where, arrays.pop("meta"))
    if "visible" not in arrays and arrays["positions"].ndim == 3:
        arrays["visible"] = np.ones(arrays["positions"].shape[:2], dtype=bool)
    arrays.setdefault("visible", np.ones(0, dtype=bool))     # positions' shape error comes first
    _check_arrays(where, arrays, params)
    return Recording(
        positions=torch.from_numpy(arrays["positions"].astype(np.float64)),
        times=torch.from_numpy(arrays["times"].astype(np.float64)),
        move_node=torch.from_numpy(arrays["move_node"].astype(np.int64)),
        move_delta=torch.from_numpy(arrays["move_delta"].astype(np.float64)),
        move_start=torch.from_numpy(arrays["move_start"].astype(np.int64)),
        move_end=torch.from_numpy(arrays["move_end"].astype(np.int64)),
        visible=torch.from_numpy(arrays["visible"].astype(bool)),
        meta=meta,
    )


def recording_arrays(rec: Recording) -> dict[str, np.ndarray]:
    """The arrays ``save_recording`` writes (numpy, the file's dtypes, ``meta`` as a JSON string)."""
    return {
        "positions": rec.positions.detach().cpu().numpy().astype(np.float64),
        "times": rec.times.detach().cpu().numpy().astype(np.float64),
        "move_node": rec.move_node.cpu().numpy().astype(np.int64),
        "move_delta": rec.move_delta.detach().cpu().numpy().astype(np.float64),
        "move_start": rec.move_start.cpu().numpy().astype(np.int64),
        "move_end": rec.move_end.cpu().numpy().astype(np.int64),
        "visible": rec.visible.cpu().numpy().astype(bool),
        "meta": np.array(json.dumps(rec.meta)),
    }


def save_recording(path: Path | str, rec: Recording) -> None:
    """Check ``rec`` as ``load_recording`` would, then write it to ``path`` atomically (a temporary ``.npz`` beside
    it, then renamed over it). Raises RecordingError, naming the field, for a recording the loader would refuse."""
    arrays = recording_arrays(rec)
    where = f"recording for {path}"
    _parse_meta(where, arrays["meta"])
    _check_arrays(where, {k: v for k, v in arrays.items() if k != "meta"}, None)
    with replacing(path, suffix=".npz") as tmp:             # the suffix stops np.savez from appending one
        np.savez(tmp, **arrays)
