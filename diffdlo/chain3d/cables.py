"""The 3-D chain's cables: DEFORM's five real cables as parameter files (params/cables3d.yaml), loaded and checked.

``load_cable("DLO3")`` (or None: the file's default) returns a ``Cable``: the chain's ``ChainParams`` (a node per
marker, the fitted EI, EA, drag and dampings), its substeps per 10 ms frame, the held markers, and each fitted
number's spread, so the 3-D task (diffdlo/tasks/cable3d.py) runs a cable known to predict real recordings to about a
centimetre (docs/REAL_CABLE.md) without DEFORM's data. A bad file or value is refused naming it (CableError).

    python -m diffdlo.chain3d.cables                          # the cables and their numbers
    python -m diffdlo.chain3d.cables --data DEFORM/data_set   # each cable's rest lengths from its train recordings
    python -m diffdlo.chain3d.cables --data DEFORM/data_set --speeds   # how fast its markers move when recorded
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

import torch
import yaml

from ..planar.params import PARAMS_DIR
from .chain import ChainError, ChainParams, stability_margin
from .deform import CABLES

CABLES_FILE = "cables3d.yaml"
FITTED = ("EI", "EA", "drag", "axial_damping", "bending_damping")
FRAME_DT = 0.01                       # [s] DEFORM's 100 Hz, the fit's frame


class CableError(ValueError):
    """A cables file, a cable name or a value that cannot be used; the message names it."""


@dataclasses.dataclass(frozen=True)
class Cable:
    """One cable of the 3-D chain: its chain, how to integrate it, what the grippers hold."""
    name: str
    params: ChainParams               # float64 rest lengths and point masses, float fitted values
    substeps: int                     # per FRAME_DT frame
    held: tuple[int, ...]             # held marker (node) indices, non-negative, two at each end
    length: float                     # [m] the paper's
    mass: float                       # [kg] the paper's
    spread: dict[str, float | None]   # bootstrap factor of each fitted value (None: at the fit's bound)

    @property
    def n_nodes(self) -> int:
        return int(self.params.rest_lengths.shape[-1]) + 1


def _number(where: str, value: Any, lower: float = 0.0, inclusive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
            value >= lower if inclusive else value > lower):
        raise CableError(f"{where} must be a finite number {'>=' if inclusive else '>'} {lower:g}, got {value!r}")
    return float(value)


def _read(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise CableError(f"cannot read the cables file {path}: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("cables"), dict) or not data["cables"]:
        raise CableError(f"{path}: must hold a mapping 'cables' of cable name -> its numbers")
    return data


def cable_names(path: Path | str | None = None) -> list[str]:
    """The cables of the file (default params/cables3d.yaml)."""
    return sorted(_read(Path(path) if path else PARAMS_DIR / CABLES_FILE)["cables"])


def load_cable(name: str | None = None, path: Path | str | None = None) -> Cable:
    """Cable ``name`` of the cables file (default params/cables3d.yaml; None: the file's ``default``), checked:
    CableError naming the file, the cable and the field for anything missing, unknown or out of range."""
    path = Path(path) if path else PARAMS_DIR / CABLES_FILE
    data = _read(path)
    cables = data["cables"]
    name = data.get("default") if name is None else name
    if name not in cables:
        raise CableError(f"unknown cable {name!r}: use one of {sorted(cables)} ({path})")
    entry = cables[name]
    where = f"{path}: cable {name}"
    if not isinstance(entry, dict):
        raise CableError(f"{where}: must be a mapping of its numbers, got {entry!r}")
    known = {"length", "mass", "stiffness_rank", "rest_lengths", "substeps", *FITTED}
    missing, unknown = known - {"stiffness_rank"} - set(entry), set(entry) - known
    if missing or unknown:
        raise CableError(f"{where}: " + "; ".join(
            ([f"missing {sorted(missing)}"] if missing else []) + ([f"unknown {sorted(unknown)}"] if unknown else [])))
    length, mass = _number(f"{where}: length [m]", entry["length"]), _number(f"{where}: mass [kg]", entry["mass"])
    rest = entry["rest_lengths"]
    if not isinstance(rest, list) or len(rest) < 4:
        raise CableError(f"{where}: rest_lengths must be a list of at least 4 link lengths [m], got {rest!r}")
    rest = [_number(f"{where}: rest_lengths[{i}] [m]", v) for i, v in enumerate(rest)]
    substeps = entry["substeps"]
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise CableError(f"{where}: substeps must be an integer >= 1, got {substeps!r}")
    values, spread = {}, {}
    for key in FITTED:
        item = entry[key]
        if not isinstance(item, dict) or set(item) != {"value", "spread"}:
            raise CableError(f"{where}: {key} must be {{value: number, spread: factor or bound}}, got {item!r}")
        values[key] = _number(f"{where}: {key}", item["value"], 0.0, inclusive=key != "EA")
        spread[key] = None if item["spread"] == "bound" else _number(f"{where}: {key}'s spread", item["spread"], 1.0,
                                                                    inclusive=True)
    marker_mass = _number(f"{path}: marker_mass [kg]", data.get("marker_mass", 0.0), 0.0, inclusive=True)
    n = len(rest) + 1
    held_raw = data.get("held_markers", [0, 1, -2, -1])
    if (not isinstance(held_raw, list) or len(held_raw) != 4
            or any(isinstance(h, bool) or not isinstance(h, int) or not -n <= h < n for h in held_raw)):
        raise CableError(f"{path}: held_markers must be 4 marker indices in [-{n}, {n}), got {held_raw!r}")
    held = tuple(sorted(h % n for h in held_raw))
    if held != (0, 1, n - 2, n - 1):
        raise CableError(f"{path}: held_markers must be the two markers at each end (0, 1, -2, -1), got {held_raw!r}")
    params = ChainParams(rest_lengths=torch.tensor(rest, dtype=torch.float64), mass_per_length=mass / length,
                         point_mass=marker_mass, **values)
    try:
        params.check(1, n)
    except ChainError as exc:
        raise CableError(f"{where}: {exc}") from exc
    held_mask = torch.zeros(n, dtype=torch.bool)
    held_mask[list(held)] = True
    # the links between two held markers never move under the chain's forces: out of the shortest rest length (as
    # the fit's CableModel.stability)
    rigid = held_mask[:-1] & held_mask[1:]
    free_rest = torch.where(rigid, params.rest_lengths.max(), params.rest_lengths)
    margin = stability_margin(dataclasses.replace(params, rest_lengths=free_rest), n, FRAME_DT / substeps, held_mask)
    if margin >= 1.0:
        raise CableError(f"{where}: {substeps} substeps per {FRAME_DT * 1e3:g} ms frame are unstable at these "
                         f"values (stability_margin {margin:.3g}, must be < 1): raise substeps")
    return Cable(name=str(name), params=params, substeps=substeps, held=held, length=length, mass=mass,
                 spread=spread)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m diffdlo.chain3d.cables", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="DEFORM's data_set folder: print each cable's rest lengths (the median "
                                              "marker gaps of its train recordings, as the fit's chain)")
    ap.add_argument("--speeds", action="store_true", help="with --data: how fast each cable's markers move in its "
                                                          "eval recordings (quantiles of the fastest free and held "
                                                          "marker's speed per frame): whether any frame is at rest")
    args = ap.parse_args(argv)
    if args.speeds and args.data is None:
        ap.error("--speeds needs --data")
    if args.speeds:
        from .deform import RecordingError, load_split, marker_speeds
        levels = (0.0, 0.01, 0.1, 0.5)
        print(f"fastest marker speed per frame [m/s] (central differences), quantiles {levels}")
        for number, spec in sorted(CABLES.items()):
            try:
                recordings = load_split(args.data, number, "eval")
            except RecordingError as exc:
                ap.error(str(exc))
            v = torch.cat([marker_speeds(x) for x in recordings.values()])
            q = torch.tensor(levels, dtype=v.dtype)
            free, held = torch.quantile(v[:, 2:-2].amax(-1), q), torch.quantile(v[:, [0, -1]].amax(-1), q)
            print(f"{spec.name}: {v.shape[0]} frames; free markers {[round(x, 3) for x in free.tolist()]}, held "
                  f"ends {[round(x, 3) for x in held.tolist()]}")
        return 0
    if args.data is not None:
        from .deform import RecordingError, load_split
        from .fit import cable_model
        for number, spec in sorted(CABLES.items()):
            try:
                model = cable_model(load_split(args.data, number, "train"), mass=spec.mass, length=spec.length)
            except RecordingError as exc:
                ap.error(str(exc))
            print(f"{spec.name}: rest_lengths: [{', '.join(f'{v:.5f}' for v in model.rest_lengths.tolist())}]"
                  f"  substeps: {model.substeps}")
        return 0
    for name in cable_names():
        c = load_cable(name)
        fitted = ", ".join(f"{k} {getattr(c.params, k):g}" + (" (bound)" if c.spread[k] is None else
                                                              f" x/ {c.spread[k]:g}") for k in FITTED)
        print(f"{name}: {c.n_nodes} markers, {float(c.params.rest_lengths.sum()):.3f} m between the end markers, "
              f"{c.mass * 1e3:g} g, {c.substeps} substeps; {fitted}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
