"""The evaluations of eval.csv for /history, read as the file grows.

/history is rendered about once a second while a dashboard is open, and
eval.csv grows by a row per evaluation for the whole run: reading it whole
each time costs the learner's process (its updates) more the longer the run.
`EvalSeries` reads only the rows appended since its last read, and starts over
when the file is cut (a resumed run drops rows) or replaced. Beyond
`MAX_EVALS` evaluations it serves an evenly spaced subset (every second,
fourth, ...), the first and the newest always in it; eval.csv keeps every row.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

MAX_EVALS = 2000
"""Evaluations /history gives at most (a chart's width in points); eval.csv keeps them all."""


class EvalSeries:
    def __init__(self, path: Path, max_evals: int = MAX_EVALS) -> None:
        self.path, self.max_evals = Path(path), max_evals
        self._evals: list[dict] = []
        self._fields: list[str] | None = None
        self._offset = 0  # bytes read: the header and every whole line after it
        self._file: tuple[int, int] | None = None  # (device, inode) of the file read
        self._last = b""  # the last whole line read: still there, or the file was rewritten under it
        self.lines_read = 0  # lines parsed since the start (a test's measure of the work done)

    def __call__(self) -> list[dict]:
        """step, mean and std of each evaluation (a row still being written is left for the next call)."""
        try:
            st = os.stat(self.path)
        except OSError:
            self._start_over(None)
            return []
        if (st.st_dev, st.st_ino) != self._file or st.st_size < self._offset:
            self._start_over((st.st_dev, st.st_ino))
        # Read at the size last read too: a file cut and written again to that size holds other rows.
        try:
            new = self._read_on()
        except OSError:
            return thin(self._evals, self.max_evals)
        whole = new[: new.rfind(b"\n") + 1]
        self._offset += len(whole)
        lines = whole.splitlines(keepends=True)
        for line in lines:
            self._take(line.rstrip(b"\r\n"))
        self._last = lines[-1] if lines else self._last
        return thin(self._evals, self.max_evals)

    def _read_on(self) -> bytes:
        """The bytes after those read; all of them, from a fresh start, if the last line read is no
        longer where it was (a resume cut the file and rows were appended since)."""
        with open(self.path, "rb") as f:
            f.seek(self._offset - len(self._last))
            if f.read(len(self._last)) != self._last:
                self._start_over(self._file)
                f.seek(0)
            return f.read()

    def _start_over(self, file: tuple[int, int] | None) -> None:
        self._evals, self._fields, self._offset, self._file, self._last = [], None, 0, file, b""

    def _take(self, line: bytes) -> None:
        """One line of the file: the header first, then an evaluation (a damaged one is skipped)."""
        self.lines_read += 1
        try:
            values = next(csv.reader([line.decode("utf-8")]), [])
        except (UnicodeDecodeError, csv.Error):  # undecodable, or past csv's field limit
            values = None
        if self._fields is None:
            self._fields = values or []
            return
        row = dict(zip(self._fields, values or [], strict=False))
        try:
            e = {"step": int(row["step"]), "mean": float(row["mean"]), "std": float(row["std"])}
        except (KeyError, TypeError, ValueError):
            return
        if math.isfinite(e["mean"]):
            self._evals.append(e)


def thin(evals: list[dict], most: int) -> list[dict]:
    """At most `most` of `evals`: every `stride`-th from the first, and the newest. The stride is a
    power of two, so the points a dashboard draws stay where they are as evaluations come, until
    the stride doubles (as the learner's own series thins)."""
    if len(evals) <= most:
        return list(evals)
    if most < 2:
        return evals[-most:] if most else []
    stride = 1
    while (len(evals) - 1) // stride + 1 >= most:  # room for the newest besides
        stride *= 2
    out = evals[::stride]
    return out if out[-1] is evals[-1] else [*out, evals[-1]]
