"""The learner's view of the run, fed by its Zenoh callbacks and its loop, and the /status it serves.

`StatusBoard` holds what the rest of the system reports (replay stats, the
actors' heartbeats and liveliness, invalid messages) and what the loop
measures (losses, policy lag, rates). Callbacks run on Zenoh's threads, so
every field they touch is guarded by one lock.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections import deque

import numpy as np

from shared import wire
from shared.writes import WriteFailures

RATE_SAMPLE_S = 0.5
RATE_WINDOW_S = 10.0
STALE_SAMPLE_S = 2 * RATE_SAMPLE_S
"""A newest sample older than this means the loop stopped sampling: the rates end at now."""
MAX_ACTORS = 1024
"""Actor ids the board holds. A new id beyond takes the place of those gone longest (not alive), or
is left out while every id held is alive: heartbeats of ever new ids (a bug, a forged message)
must not grow /status, and the lock and encoding that every read of it costs, without bound."""


def _new_actor(actor_id: int, incarnation: int) -> dict:
    return {"id": actor_id, "incarnation": incarnation, "alive": True, "env_steps": 0, "episodes": 0,
            "last_seen": time.monotonic(), "policy_version": 0, "steps_per_s": 0.0, "refused": 0,
            "fault": None, "env_step_seconds": None}


def step_histogram(counts: list[int], total_s: float) -> dict | None:
    """An actor's env step times as /status shows them: count, sum, and the cumulative count at
    each bucket's upper bound (Prometheus' `le`, "+Inf" last); None when it sent none."""
    if not counts:
        return None
    bounds = [*(str(b) for b in wire.STEP_SECONDS_BUCKETS), "+Inf"]
    # Python's integers: the wire allows counts whose sum passes int64's range, where np.cumsum
    # would wrap to negative, decreasing buckets.
    cumulative = list(itertools.accumulate(counts))
    le = dict(zip(bounds, cumulative, strict=True))
    return {"count": int(cumulative[-1]), "sum": round(total_s, 6), "le": le}


class StatusBoard:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.writes = WriteFailures()
        self.env_steps = 0
        self.replay = {"size": 0, "bytes": 0, "done": False, "invalid": 0, "dropped": 0, "inserts": 0,
                       "samples": 0, "write_error": ""}
        self.actors: dict[int, dict] = {}
        self.restarts: dict[int, deque[float]] = {}  # actor id -> when its recent new incarnations came
        self._tokens: dict[int, deque[int]] = {}  # actor id -> incarnations whose token was seen
        self.invalid = 0
        self.losses: dict[str, float] = {}
        # Non-finite values met by the loop: skipped updates, dropped batches, and per loss how
        # often it was non-finite and its last such value ("nan", "inf", "-inf"), so /status shows them.
        self.skipped_updates = 0
        self.dropped_batches = 0
        self.dropped_rows: list[int] = []
        self.nonfinite_losses: dict[str, dict] = {}
        self.last_update = time.monotonic()
        self.evaluating = False  # an evaluation between updates is under way
        self.lag = {"mean": None, "max": None}
        self._rates: deque[tuple[float, int, int]] = deque(maxlen=64)

    # -- what the system reports ----------------------------------------------------

    def replay_stats(self, s: wire.ReplayStats) -> None:
        with self._lock:
            self.env_steps = max(self.env_steps, s.num_inserted)
            self.replay = {"size": s.size, "bytes": s.bytes, "done": s.done, "invalid": s.invalid,
                           "dropped": s.dropped, "inserts": s.inserts, "samples": s.samples,
                           "write_error": s.write_error}

    def seen_env_steps(self, n: int) -> None:
        with self._lock:
            self.env_steps = max(self.env_steps, n)

    def actor_status(self, s: wire.ActorStatus) -> None:
        """A heartbeat; a newer incarnation of an actor id replaces the older one."""
        with self._lock:
            a = self.actors.get(s.actor_id)
            if a is None and not self._make_room():
                return
            if a is None or s.incarnation > a["incarnation"]:
                # Alive only once its liveliness token is seen: a heartbeat alone is no process.
                a = self._new_incarnation(a, s.actor_id, s.incarnation, token=False)
            if s.incarnation == a["incarnation"]:
                a.update(env_steps=s.env_steps, policy_version=s.policy_version,
                         steps_per_s=round(s.steps_per_s, 2), episodes=s.episodes, refused=s.refused,
                         last_seen=time.monotonic(),
                         fault=s.fault, env_step_seconds=step_histogram(s.step_counts, s.step_seconds))

    def actor_alive(self, actor_id: int, incarnation: int, alive: bool) -> None:
        """An actor's liveliness token appeared (alive) or went away."""
        with self._lock:
            a = self.actors.get(actor_id)
            if a is None and (not alive or not self._make_room()):
                return
            if alive:
                self._token_seen(actor_id, incarnation)
            if alive and (a is None or incarnation > a["incarnation"]):
                self._new_incarnation(a, actor_id, incarnation, token=True)
            elif a is not None and incarnation == a["incarnation"]:
                a["alive"] = alive
                a["last_seen"] = time.monotonic()

    def _make_room(self) -> bool:
        """Under the lock: whether a new actor id may be held (MAX_ACTORS). A full board forgets the
        ids gone longest (not alive) down to half of it at once, so a flood costs one scan per
        MAX_ACTORS / 2 new ids, not one each."""
        if len(self.actors) < MAX_ACTORS:
            return True
        gone = sorted((a for a in self.actors.values() if not a["alive"]), key=lambda a: a["last_seen"])
        for a in gone[:len(self.actors) - MAX_ACTORS // 2]:
            del self.actors[a["id"]]
            self.restarts.pop(a["id"], None)
            self._tokens.pop(a["id"], None)
        return len(self.actors) < MAX_ACTORS

    def _token_seen(self, actor_id: int, incarnation: int) -> None:
        """A liveliness token of an incarnation: after the actor id's first, each new one is a restart."""
        seen = self._tokens.setdefault(actor_id, deque(maxlen=16))
        if incarnation in seen:
            return
        if seen:
            self.restarts.setdefault(actor_id, deque(maxlen=16)).append(time.monotonic())
        seen.append(incarnation)

    def _new_incarnation(self, old: dict | None, actor_id: int, incarnation: int, token: bool) -> dict:
        """An actor id's entry for a new incarnation, alive if its liveliness token came (`token`);
        under the lock."""
        a = self.actors[actor_id] = _new_actor(actor_id, incarnation)
        a["alive"] = token
        return a

    def crash_looping(self, restarts: int, within_s: float) -> list[int]:
        """Actor ids restarted (a new incarnation) more than `restarts` times in the last `within_s`."""
        now = time.monotonic()
        with self._lock:
            recent = {i: sum(now - s <= within_s for s in t) for i, t in self.restarts.items()}
        return sorted(i for i, n in recent.items() if n > restarts)

    def count_invalid(self) -> int:
        with self._lock:
            self.invalid += 1
            return self.invalid

    # -- what the loop measures --------------------------------------------------------

    def count_skipped_update(self) -> int:
        self.skipped_updates += 1
        return self.skipped_updates

    def count_nonfinite_batch(self, index: list[int]) -> int:
        """A batch dropped for non-finite values; `index`: its bad rows' global indices."""
        self.dropped_batches += 1
        self.dropped_rows = index[:64]
        return self.dropped_batches

    def record_update(self, metrics: dict[str, float]) -> None:
        self.last_update = time.monotonic()
        for key, value in metrics.items():
            if not math.isfinite(value):
                entry = self.nonfinite_losses.setdefault(key, {"count": 0, "last": ""})
                entry["count"] += 1
                entry["last"] = str(value)
                continue  # the running mean keeps the finite values
            old = self.losses.get(key)
            self.losses[key] = value if old is None else 0.95 * old + 0.05 * value

    def record_lag(self, updates: int, versions: np.ndarray) -> None:
        """Policy lag of a sampled batch: the learner's version minus the version that collected each row."""
        lag = updates - versions
        mean, worst = float(lag.mean()), int(lag.max())
        old = self.lag["mean"]
        self.lag = {"mean": mean if old is None else 0.95 * old + 0.05 * mean, "max": worst}

    def sample_rates(self, updates: int) -> None:
        """Keep (time, env steps, updates) every RATE_SAMPLE_S for the rates /status reports."""
        now = time.monotonic()
        if not self._rates or now - self._rates[-1][0] >= RATE_SAMPLE_S:
            self._rates.append((now, self.env_steps, updates))

    def rates(self) -> tuple[float, float]:
        """Env steps/s and updates/s over the last ~10 s up to now. A loop that has not sampled
        for a while (an evaluation between updates, a wait on the replay) did no updates since:
        its rates fall, rather than stand at what they were when it last sampled."""
        rates = list(self._rates)
        if not rates:
            return 0.0, 0.0
        end = rates[-1]
        now = time.monotonic()
        if now - end[0] > STALE_SAMPLE_S:
            end = (now, self.env_steps, end[2])
        t0, e0, u0 = next((r for r in rates if r[0] >= end[0] - RATE_WINDOW_S), rates[-1])
        t1, e1, u1 = end
        if t1 <= t0:
            return 0.0, 0.0
        return (e1 - e0) / (t1 - t0), (u1 - u0) / (t1 - t0)

    def snapshot(self) -> dict:
        """The fleet and replay part of /status."""
        with self._lock:
            now = time.monotonic()
            actors = [{**{k: v for k, v in a.items() if k != "last_seen"},
                       "last_seen_s": round(now - a["last_seen"], 3)}
                      for a in sorted(self.actors.values(), key=lambda a: a["id"])]
            r = dict(self.replay)
            env_steps, invalid = self.env_steps, self.invalid
        env_rate, upd_rate = self.rates()
        return {
            "env_steps": env_steps,
            "env_steps_per_s": round(env_rate, 3),
            "updates_per_s": round(upd_rate, 3),
            "replay": {"size": r["size"], "bytes": r["bytes"], "done": r["done"], "dropped": r["dropped"],
                       "invalid_messages": r["invalid"], "limiter_inserts": r["inserts"],
                       "limiter_samples": r["samples"], "write_error": r["write_error"]},
            "actors": actors,
            "policy_lag": {k: (round(v, 3) if v is not None else None) for k, v in self.lag.items()},
            # dict(...) copies in one step: the update loop may add a key while this iterates.
            "losses": {k: round(v, 6) for k, v in dict(self.losses).items() if math.isfinite(v)},
            "nonfinite": {"skipped_updates": self.skipped_updates, "dropped_batches": self.dropped_batches,
                          "dropped_rows": list(self.dropped_rows),
                          "losses": {k: dict(v) for k, v in dict(self.nonfinite_losses).items()}},
            "invalid_messages": invalid,
            "writes": self.writes.snapshot(),
        }
