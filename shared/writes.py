"""Writes of the run folder the disk refused (a full or read-only disk), counted by kind.

A service that goes on past a refused write (the learner's CSV rows, TensorBoard points and
checkpoints; the evaluator's pictures) counts it here: how many of each kind, the last error and
when it came, and which kinds fail still (no write of theirs has succeeded since). The learner
shows its own and what the evaluator reports with its results (/status `writes`, /metrics, /healthz
degraded).
"""

from __future__ import annotations

import threading
import time


class WriteFailures:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._failing: set[str] = set()
        self._reported: dict[str, tuple[dict[str, int], list[str]]] = {}  # source -> its counts, failing
        self.last_error = ""
        self.last_error_at: float | None = None

    def failed(self, what: str, err: BaseException | str) -> None:
        text = err if isinstance(err, str) else f"{type(err).__name__}: {err}"
        with self._lock:
            self._counts[what] = self._counts.get(what, 0) + 1
            self._failing.add(what)
            self.last_error, self.last_error_at = f"{what}: {text}", time.time()

    def ok(self, what: str) -> None:
        """A write of `what` succeeded: it no longer fails."""
        if what in self._failing:
            with self._lock:
                self._failing.discard(what)

    def report(self, source: str, counts: dict[str, int], failing: list[str], last_error: str) -> None:
        """What another process (`source`) counted of its own refused writes since it started; each
        report replaces the one before. Its kinds show as `<source>/<kind>`; a count that grew makes
        its last error the last one here."""
        with self._lock:
            before = self._reported.get(source, ({}, []))[0]
            self._reported[source] = (dict(counts), list(failing))
            if any(n > before.get(kind, 0) for kind, n in counts.items()):
                self.last_error, self.last_error_at = f"{source}/{last_error}", time.time()

    def _all(self) -> tuple[dict[str, int], set[str]]:
        """Under the lock: this process's counts and failing kinds with those reported to it."""
        counts, failing = dict(self._counts), set(self._failing)
        for source, (theirs, still) in self._reported.items():
            counts |= {f"{source}/{kind}": n for kind, n in theirs.items()}
            failing |= {f"{source}/{kind}" for kind in still}
        return counts, failing

    def failing(self) -> list[str]:
        with self._lock:
            return sorted(self._all()[1])

    def snapshot(self) -> dict:
        with self._lock:
            counts, failing = self._all()
            at = self.last_error_at
            return {"failed": dict(sorted(counts.items())), "failing": sorted(failing),
                    "last_error": self.last_error,
                    "last_error_at": (time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(at))
                                      if at is not None else None)}
