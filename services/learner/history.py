"""The learner's recent past for the dashboard: a bounded series of /status figures.

A daemon thread reads /status every `every_s` seconds (never the update loop)
and keeps one point per read. When `capacity` points are held, every second
point is dropped and the interval doubles, so the series always spans the
whole run in at most `capacity` points. The learner leaves the series in
<data>/learner/history.json when it stops, for `nasa status --data DIR --serve`,
and a learner that resumes the run carries it on.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from pathlib import Path

from shared.files import replace_text

HISTORY_FILE = "learner/history.json"


def point(s: dict) -> dict:
    """The figures of one /status the dashboard plots."""
    intrinsic, replay, lag = s["intrinsic"], s["replay"], s["policy_lag"]
    return {
        "wall_s": s["wall_s"], "env_steps": s["env_steps"], "updates": s["updates"],
        "env_steps_per_s": s["env_steps_per_s"], "updates_per_s": s["updates_per_s"],
        "updates_per_env_step": s["updates_per_env_step"], "target": s["updates_target_per_env_step"],
        "lag_mean": lag["mean"], "lag_max": lag["max"],
        "novelty_mean": intrinsic["novelty_mean"], "surprise_mean": intrinsic["surprise_mean"],
        "replay_size": replay["size"], "replay_bytes": replay["bytes"],
        "invalid_messages": s["invalid_messages"], "replay_invalid_messages": replay["invalid_messages"],
        "losses": dict(s["losses"]),
    }


class History:
    def __init__(self, capacity: int = 1000, every_s: float = 2.0) -> None:
        self.capacity, self.every_s = capacity, every_s
        self._points: list[dict] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.failed_reads, self.last_error = 0, ""

    def add(self, status: dict) -> None:
        with self._lock:
            self._points.append(point(status))
            self._thin()

    def _thin(self) -> None:
        """Under the lock: every second point dropped, and the interval doubled, until below capacity."""
        while len(self._points) >= self.capacity:
            self._points = self._points[::2]
            self.every_s *= 2

    def restore(self, data: Path, wall_s: float) -> None:
        """Carry on the series an earlier learner of the run left, up to `wall_s` (the run's clock
        at the checkpoint resumed from: later points belong to steps that will run again).
        HistoryError if it cannot be read."""
        body = _read(data)
        if body is None:
            return
        points = [p for p in body["points"]
                  if isinstance(p.get("wall_s"), int | float) and p["wall_s"] <= wall_s]
        every_s = body.get("every_s")
        with self._lock:
            self._points = points + self._points
            # The interval doubles only once the series is full, so it never exceeds the time the run
            # has lasted: a longer one is a damaged file, and waiting it out would end the series.
            if isinstance(every_s, int | float) and math.isfinite(every_s) \
                    and self.every_s < every_s <= max(wall_s, self.every_s):
                self.every_s = float(every_s)
            self._thin()

    def points(self) -> list[dict]:
        with self._lock:
            return list(self._points)

    def start(self, status: Callable[[], dict]) -> None:
        """Read `status` every `every_s` seconds on a daemon thread until `stop`."""
        def run() -> None:
            while not self._stop.wait(self.every_s):
                self._read(status)

        self._read(status)
        self._thread = threading.Thread(target=run, name="history", daemon=True)
        self._thread.start()

    def _read(self, status: Callable[[], dict]) -> None:
        try:
            self.add(status())
        except Exception as err:  # noqa: BLE001 -- one bad read must not end the series (nor the learner)
            self.failed_reads += 1
            self.last_error = f"{type(err).__name__}: {err}"

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def save(self, data: Path) -> None:
        """Write the series to <data>/learner/history.json (atomically)."""
        path = Path(data) / HISTORY_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        replace_text(path, json.dumps({"every_s": self.every_s, "points": self.points()}))


class HistoryError(ValueError):
    """A history.json that cannot be read (damaged, or not one the learner wrote)."""


def _read(data: Path) -> dict | None:
    """The history.json an earlier learner left ({"every_s", "points"}), or None."""
    path = Path(data) / HISTORY_FILE
    if not path.exists():
        return None
    try:
        body = json.loads(path.read_bytes())
        points = body["points"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise HistoryError(f"{path} is unreadable ({type(err).__name__}: {err})") from err
    if not isinstance(points, list) or not all(isinstance(p, dict) for p in points):
        raise HistoryError(f"{path} is unreadable: its points are not a list of objects")
    return body


def load(data: Path) -> list[dict]:
    """A stopped run's series (empty if the learner left none)."""
    body = _read(data)
    return [] if body is None else body["points"]
