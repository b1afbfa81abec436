"""DEFORM's motion-capture recordings of real cables, read safely.

DEFORM (Chen et al., "Differentiable Discrete Elastic Rods for Real-Time Modeling of Deformable Linear Objects",
CoRL 2024, github.com/roahmlab/DEFORM) recorded five cables (DLO1 ... DLO5) swung by two robot arms, with a
motion-capture system tracking markers along each cable. Its repository holds them as

    data_set/DLO{1..5}/{train,eval}/<id>.pkl

each a pickled plain nested list of floats of shape (T, 3, n): T = 500 frames at 100 Hz (``DT``), the x, y, z rows
in metres (z up), n markers along the cable (13 on DLO1, 12 on DLO2-5). The two markers at each end
(``HELD_MARKERS``) are held by the robots' grippers. That repository has no licence, so this project never commits
the recordings: commands read them from a directory the user gives.

A pickle can run any code when it is loaded, so these files are read in two guarded steps. First every opcode of
the file is checked against ``DATA_OPCODES``, the opcodes that build the pickle format's own containers and scalars
(no import, no call, no object state, no persistent id, no extension code: ``copyreg``'s extension cache would hand
back an object without asking ``find_class``); then ``SafeUnpickler``, whose ``find_class`` refuses every class and
function, builds it. ``load_recording`` then accepts nothing but the rectangular (T, 3, n) nested list/tuple of
finite numbers. Anything else raises ``RecordingError`` naming the file and the problem.
"""
from __future__ import annotations

import dataclasses
import io
import math
import pickle
import pickletools
from pathlib import Path
from typing import Any

import torch

DT = 0.01                         # [s] between frames: DEFORM's recordings are at 100 Hz
HELD_MARKERS = (0, 1, -2, -1)     # marker indices held by the robots' grippers (two at each end)
SPLITS = ("train", "eval")
MAX_FILE_BYTES = 64 * 2 ** 20     # a (500, 3, 13) recording pickles to ~0.2 MB; refuse anything absurdly larger

# Markers: spheres of this diameter [m] and mass [kg] each (the DEFORM paper's experimental setup).
MARKER_DIAMETER = 7.9e-3
MARKER_MASS = 0.4e-3


@dataclasses.dataclass(frozen=True)
class DeformCable:
    """One of DEFORM's cables as its paper describes it (SI units)."""
    name: str
    length: float             # [m]
    mass: float               # [kg], as the paper's table gives it (it does not say whether the markers are in it)
    stiffness_rank: int       # 1 the softest ... 5 the stiffest, the paper's ordering (no measured EI is given)
    n_markers: int            # markers tracked along it in the recordings

    @property
    def mass_per_length(self) -> float:
        """[kg/m] the table's mass over its length."""
        return self.mass / self.length


# The DEFORM paper's table of the five cables (Chen et al., CoRL 2024): length, weight and the stiffness ordering
# (DLO5 the stiffest, DLO4 the softest). The marker counts are those of the recordings (13 on DLO1, 12 on the others).
CABLES: dict[int, DeformCable] = {
    1: DeformCable("DLO1", length=1.152, mass=34.5e-3, stiffness_rank=3, n_markers=13),
    2: DeformCable("DLO2", length=0.996, mass=65.2e-3, stiffness_rank=4, n_markers=12),
    3: DeformCable("DLO3", length=0.998, mass=96.8e-3, stiffness_rank=5, n_markers=12),
    4: DeformCable("DLO4", length=0.973, mass=22.0e-3, stiffness_rank=1, n_markers=12),
    5: DeformCable("DLO5", length=0.988, mass=19.2e-3, stiffness_rank=2, n_markers=12),
}


class RecordingError(ValueError):
    """A DEFORM recording (or a folder of them) that cannot be read; the message names the file and the problem."""


# Opcodes that only build builtin data (numbers, strings, bytes, None, booleans, lists, tuples, dicts, sets), or
# handle the stack, the memo and framing. Every other opcode imports, calls or sets state (GLOBAL, STACK_GLOBAL,
# REDUCE, BUILD, INST, OBJ, NEWOBJ*, EXT*, PERSID*, buffers) and is refused before anything is built.
DATA_OPCODES = frozenset({
    "PROTO", "FRAME", "STOP", "MARK", "POP", "POP_MARK", "DUP", "PUT", "BINPUT", "LONG_BINPUT", "MEMOIZE", "GET",
    "BINGET", "LONG_BINGET", "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "FLOAT", "BINFLOAT",
    "NONE", "NEWTRUE", "NEWFALSE", "STRING", "BINSTRING", "SHORT_BINSTRING", "UNICODE", "BINUNICODE",
    "SHORT_BINUNICODE", "BINUNICODE8", "BINBYTES", "SHORT_BINBYTES", "BINBYTES8", "BYTEARRAY8", "EMPTY_LIST",
    "LIST", "APPEND", "APPENDS", "EMPTY_TUPLE", "TUPLE", "TUPLE1", "TUPLE2", "TUPLE3", "EMPTY_DICT", "DICT",
    "SETITEM", "SETITEMS", "EMPTY_SET", "ADDITEMS", "FROZENSET",
})


def check_opcodes(raw: bytes) -> None:
    """pickle.UnpicklingError naming the first opcode of ``raw`` outside ``DATA_OPCODES`` (with the global it would
    import, where it names one); nothing is built or run."""
    strings: list[str] = []
    for op, arg, pos in pickletools.genops(raw):
        if op.name not in DATA_OPCODES:
            named = arg if op.name != "STACK_GLOBAL" else ".".join(strings[-2:])
            what = f" {named!r}" if named is not None else ""
            raise pickle.UnpicklingError(f"refused opcode {op.name}{what} at byte {pos} (a recording holds plain "
                                         f"nested lists of numbers only: nothing may be imported or called)")
        if isinstance(arg, str):
            strings.append(arg)


class SafeUnpickler(pickle.Unpickler):
    """An unpickler that builds only the pickle format's own containers and scalars: every global (a class, a
    function such as ``os.system``, a numpy array's reconstructor) is refused before it is imported, so nothing
    the file names is ever called. Persistent ids are refused by the base class (no ``persistent_load``)."""

    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(f"refused to load the global {module}.{name} (a recording holds plain nested "
                                     f"lists of numbers only)")


def _type_name(value: Any) -> str:
    return type(value).__name__


def _number(where: str, value: Any, index: tuple[int, int, int]) -> float:
    t, axis, marker = index
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RecordingError(f"{where}: frame {t}, row {'xyz'[axis]}, marker {marker} holds a {_type_name(value)}, "
                             f"not a number")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise RecordingError(f"{where}: frame {t}, row {'xyz'[axis]}, marker {marker} is {value!r}, not finite")
    return number


def _values(where: str, data: Any) -> list[list[list[float]]]:
    """``data`` checked to be a rectangular (T, 3, n) nested list/tuple of finite numbers, as floats."""
    sequences = (list, tuple)
    if not isinstance(data, sequences):
        raise RecordingError(f"{where}: holds a {_type_name(data)}, not a nested list of shape (T, 3, n)")
    if len(data) < 2:
        raise RecordingError(f"{where}: holds {len(data)} frame(s), need at least 2 (shape (T, 3, n), T >= 2)")
    n_markers = None
    frames = []
    for t, frame in enumerate(data):
        if not isinstance(frame, sequences):
            raise RecordingError(f"{where}: frame {t} is a {_type_name(frame)}, not a list of 3 rows (x, y, z): "
                                 f"the recording must have shape (T, 3, n), not rank 1")
        if len(frame) != 3:
            raise RecordingError(f"{where}: frame {t} has {len(frame)} rows, need 3 (x, y, z): the recording must "
                                 f"have shape (T, 3, n) (is it (T, n, 3)?)")
        rows = []
        for axis, row in enumerate(frame):
            if not isinstance(row, sequences):
                raise RecordingError(f"{where}: frame {t}, row {'xyz'[axis]} is a {_type_name(row)}, not a list of "
                                     f"marker coordinates: the recording must have shape (T, 3, n), not rank 2")
            if n_markers is None:
                n_markers = len(row)
                if n_markers < 4:
                    raise RecordingError(f"{where}: holds {n_markers} marker(s) per frame, need at least 4 (two "
                                         f"held at each end)")
            elif len(row) != n_markers:
                raise RecordingError(f"{where}: is not rectangular: frame {t}, row {'xyz'[axis]} has {len(row)} "
                                     f"markers, frame 0 has {n_markers}")
            rows.append([_number(where, v, (t, axis, m)) for m, v in enumerate(row)])
        frames.append(rows)
    return frames


def load_recording(path: Path | str) -> torch.Tensor:
    """One DEFORM recording as a (T, n, 3) float64 tensor: frames, markers, x/y/z [m] (z up). Raises
    RecordingError naming the file for anything but a rectangular (T, 3, n) nested list of finite numbers with
    T >= 2 and n >= 4, and for a pickle that would import or call anything (which is never run)."""
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise RecordingError(f"{where}: no such recording file")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise RecordingError(f"{where}: is {size} bytes, more than a recording's limit of {MAX_FILE_BYTES}")
    raw = path.read_bytes()
    try:
        check_opcodes(raw)
        data = SafeUnpickler(io.BytesIO(raw)).load()
    except pickle.UnpicklingError as exc:
        raise RecordingError(f"{where}: not a plain pickled nested list: {exc}") from None
    except (EOFError, ValueError, TypeError, IndexError, KeyError, AttributeError, MemoryError,
            RecursionError, OverflowError) as exc:
        raise RecordingError(f"{where}: not a readable pickle: {_type_name(exc)}: {exc}") from None
    values = _values(where, data)
    return torch.tensor(values, dtype=torch.float64).transpose(1, 2).contiguous()


def marker_speeds(positions: torch.Tensor) -> torch.Tensor:
    """(T, n, 3) a recording's markers -> (T - 2, n) each marker's speed [m/s] at frames 1 ... T - 2 (central
    differences over DT)."""
    return (positions[2:] - positions[:-2]).norm(dim=-1) / (2 * DT)


def _split_dir(data_dir: Path, cable: int, split: str) -> Path:
    """data_dir/DLO{cable}/{split}, or data_dir/data_set/DLO{cable}/{split} when data_dir is DEFORM's checkout."""
    direct = data_dir / f"DLO{cable}" / split
    nested = data_dir / "data_set" / f"DLO{cable}" / split
    return nested if not direct.is_dir() and nested.is_dir() else direct


def _id_order(stem: str) -> tuple[int, int, str]:
    return (0, int(stem), "") if stem.isdigit() else (1, 0, stem)


def load_split(data_dir: Path | str, cable: int, split: str) -> dict[str, torch.Tensor]:
    """Every recording of cable ``cable`` (1-5) in ``split`` ("train" or "eval"): {id: (T, n, 3) float64 tensor},
    ordered by id (numerically where the ids are numbers). ``data_dir`` is DEFORM's ``data_set`` folder (or the
    checkout holding it). Raises RecordingError naming the path for a missing folder, an empty split, a bad
    recording, or a marker count other than the cable's (``CABLES``)."""
    if isinstance(cable, bool) or not isinstance(cable, int) or cable not in CABLES:
        raise RecordingError(f"cable must be one of {sorted(CABLES)}, got {cable!r}")
    if split not in SPLITS:
        raise RecordingError(f"split must be one of {SPLITS}, got {split!r}")
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise RecordingError(f"{data_dir}: no such folder (give DEFORM's data_set folder)")
    folder = _split_dir(data_dir, cable, split)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such folder (DEFORM keeps cable {cable}'s {split} recordings in "
                             f"data_set/DLO{cable}/{split}/)")
    files = sorted(folder.glob("*.pkl"), key=lambda p: _id_order(p.stem))
    if not files:
        raise RecordingError(f"{folder}: holds no recordings (*.pkl)")
    expected = CABLES[cable].n_markers
    recordings = {}
    for file in files:
        positions = load_recording(file)
        if positions.shape[1] != expected:
            raise RecordingError(f"{file}: has {positions.shape[1]} markers per frame, but {CABLES[cable].name} "
                                 f"carries {expected}")
        recordings[file.stem] = positions
    return recordings
