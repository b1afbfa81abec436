"""Run logs: CSV files (and TensorBoard when installed), the training-episode statistics, the progress bar's text."""
from __future__ import annotations

import csv
import io
import math
from collections import deque
from pathlib import Path

import numpy as np
import torch

from diffdlo.utils.files import write_text_atomic


class Logger:
    """CSV files ``<out>/<group>.csv`` (always) and TensorBoard scalars ``<group>/<key>`` when it is installed.

    ``resume_step``: rows logged after that step (by a run killed after its last checkpoint) are dropped, so the
    resumed run rewrites them and the CSVs read as one uninterrupted run. ``resume_rows`` (``rows`` as the checkpoint
    saved it), when given, decides instead: each file keeps its first rows up to that count, which is exact also for
    a checkpoint saved within a step (between two updates, before an evaluation). ``rows``: group -> rows written.
    """

    def __init__(self, out: Path, resume_step: int | None = None, tensorboard: bool = True,
                 resume_rows: dict[str, int] | None = None):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.fields: dict[str, list[str]] = {}
        self.rows: dict[str, int] = {}
        for path in self.out.glob("*.csv"):
            rows = read_csv(path)
            if resume_step is None:
                path.unlink()
                continue
            if resume_rows is not None:
                keep = rows[:resume_rows.get(path.stem, 0)]
            else:
                keep = [r for r in rows if float(r["step"]) <= resume_step]
            self.rows[path.stem] = len(keep)
            text = io.StringIO()
            if rows:
                w = csv.DictWriter(text, fieldnames=list(rows[0].keys()))
                w.writeheader()
                w.writerows(keep)
                self.fields[path.stem] = list(rows[0].keys())
            write_text_atomic(path, text.getvalue())      # a kill now leaves the old file or the new, whole
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self.tb = SummaryWriter(str(self.out / "tb"), purge_step=resume_step)
            except ImportError:
                self.tb = None

    def log(self, group: str, step: int, values: dict[str, float]) -> None:
        row = {"step": step, **{k: float(v) for k, v in values.items()}}
        path = self.out / f"{group}.csv"
        new = group not in self.fields
        if new:
            self.fields[group] = list(row.keys())
        with open(path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.fields[group], extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(row)
        self.rows[group] = self.rows.get(group, 0) + 1
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(f"{group}/{k}", float(v), step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def read_csv(path: Path | str) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


class EpisodeStats:
    """The last ``window`` finished training episodes (SB3's ep_info_buffer): return, length, success."""

    def __init__(self, window: int = 100):
        self.buf: deque = deque(maxlen=window)

    def add(self, info: dict[str, torch.Tensor], done: torch.Tensor) -> None:
        """Record the episodes that ended (``done``); success is ``info["is_success"]`` (a terminated episode may
        also be a failure: the env's on_exit="fail")."""
        success = info["is_success"].cpu()
        for i in done.cpu().nonzero().flatten().tolist():
            self.buf.append((float(info["ep_return"][i]), int(info["ep_length"][i]), bool(success[i])))

    def means(self) -> dict[str, float]:
        if not self.buf:
            return {}
        r, n, s = zip(*self.buf)
        return {"ep_reward": float(np.mean(r)), "ep_length": float(np.mean(n)), "success_rate": float(np.mean(s))}


def fmt_postfix(success: float | None, **extra: float) -> dict[str, str]:
    d = {"success": "n/a" if success is None or math.isnan(success) else f"{success:.2f}"}
    d.update({k: f"{v:.3g}" for k, v in extra.items()})
    return d
