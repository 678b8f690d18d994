"""The replay's reading side, one interface for both runners: sample, unscored rows, set_intrinsic.

- `LocalReplay`: over a `ReplayStore` in this process (`nasa train`, the replay
  service itself, and unit tests as the in-process fake).
- `ZenohReplayClient`: the learner's side of the replay service: sample
  requests on `replay/sample` (paced by the service's rate limiter), unscored
  requests on `replay/unscored` (not paced), scores written back on
  `replay/intrinsic` (BLOCK: a score is never dropped for congestion).
- `Prefetcher`: threads that each keep one sample request in flight and queue
  the batches, so an update finds its batch ready.

A batch (`Batch`) holds obs and next_obs (B, C*k, H, W) uint8, views into one
(B, C*(k+1), H, W) window; action (B, A) f4; reward, intrinsic (NaN: not
scored yet), discount (B,) f4; index and policy_version (B,) i8. Its arrays are
writable: the scorer fills intrinsic in place.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Protocol

import numpy as np

from shared import wire

if TYPE_CHECKING:
    from shared.envs import EnvSpec
    from shared.replay.rate_limiter import SampleToInsertRatio
    from shared.replay.store import ReplayStore
    from shared.service import Log, StopFlag

Batch = dict[str, np.ndarray]
BATCH_KEYS = ("obs", "next_obs", "action", "reward", "intrinsic", "discount", "index", "policy_version")


class ReplayClient(Protocol):
    @property
    def num_inserted(self) -> int: ...

    def sample(self, batch_size: int, wait_s: float) -> Batch | None:
        """A uniform batch, or None if none is ready within wait_s (warm-up, rate limit, no replay)."""
        ...

    def unscored(self, after: int, limit: int) -> tuple[Batch | None, int]:
        """Up to `limit` of the oldest unscored rows with global index >= after, and num_inserted
        read before the scan: every row in [after, that) not returned is scored or evicted."""
        ...

    def set_intrinsic(self, index: np.ndarray, values: np.ndarray) -> None: ...


# -- in process ------------------------------------------------------------------------------


class LocalReplay:
    """A ReplayStore in this process behind the client interface.

    `limiter`: pace samples (the inserting side counts its inserts on it); None: never wait.
    `replace=False`: batches without replacement (config.sample_without_replacement); a batch
    is then ready only once the store holds at least batch_size rows.
    """

    def __init__(
        self,
        store: ReplayStore,
        rng: np.random.Generator,
        limiter: SampleToInsertRatio | None = None,
        replace: bool = True,
    ) -> None:
        self.store = store
        self.rng = rng
        self.limiter = limiter
        self.replace = replace

    @property
    def num_inserted(self) -> int:
        return self.store.num_inserted

    def sample(self, batch_size: int, wait_s: float = 0.0) -> Batch | None:
        sampled, _ = self.draw(batch_size, wait_s)
        return None if sampled is None else batch_of(sampled)

    def draw(self, batch_size: int, wait_s: float = 0.0) -> tuple[dict[str, np.ndarray] | None, str]:
        """(what ReplayStore.sample returns, "") or (None, why not): the replay service sends the
        former's frame window as it is. Raises RateLimiterClosed if the limiter was closed."""
        if not self.replace and len(self.store) < batch_size:
            return None, f"fewer than {batch_size} rows stored (sampling without replacement)"
        if self.limiter is not None:
            if not self.limiter.take_sample(1, timeout=wait_s):
                return None, "rate limited"
        elif len(self.store) == 0:
            return None, "empty"
        return self.store.sample(batch_size, self.rng, replace=self.replace), ""

    def unscored(self, after: int, limit: int) -> tuple[Batch | None, int]:
        n = self.store.num_inserted  # read first: anything newer is past the scan
        index = self.store.unscored(after, limit)
        if len(index) == 0:
            return None, n
        return batch_of(self.store.get(index)), n

    def set_intrinsic(self, index: np.ndarray, values: np.ndarray) -> None:
        self.store.set_intrinsic(index, values)


def batch_of(sampled: dict[str, np.ndarray]) -> Batch:
    """The client's batch keys of what ReplayStore.sample/get return."""
    return {key: sampled[key] for key in BATCH_KEYS}


# -- on the wire -----------------------------------------------------------------------------


def encode_reply(sampled: dict[str, np.ndarray], num_inserted: int) -> wire.SampleReply:
    """A SampleReply of what ReplayStore.sample/get return (its `window` travels, not obs/next_obs)."""
    window = sampled["window"]
    return wire.SampleReply(
        ok=True,
        reason="",
        num_inserted=num_inserted,
        batch_size=len(window),
        window_shape=list(window.shape),
        window=window.tobytes(),
        action=sampled["action"].astype("<f4").tobytes(),
        reward=sampled["reward"].astype("<f4").tobytes(),
        intrinsic=sampled["intrinsic"].astype("<f4").tobytes(),
        discount=sampled["discount"].astype("<f4").tobytes(),
        index=sampled["index"].astype("<i8").tobytes(),
        policy_version=sampled["policy_version"].astype("<i8").tobytes(),
    )


def decode_reply(r: wire.SampleReply, spec: EnvSpec) -> Batch:
    """The batch of an ok reply, checked against the run's EnvSpec; WireError if it does not fit."""
    b, k = r.batch_size, spec.frame_stack
    c, h, w = spec.frame_shape
    shape = tuple(r.window_shape)
    expected = (b, c * (k + 1), h, w)
    if b < 1 or shape != expected:
        raise wire.WireError(f"window shape {shape}, expected {expected} for a batch of {b}")
    window = wire.array(r.window, "u1", shape).copy()  # one writable copy; obs, next_obs view it
    return {
        "obs": window[:, : c * k],
        "next_obs": window[:, c:],
        "action": wire.array(r.action, "<f4", (b, spec.action_dim)).copy(),
        "reward": wire.array(r.reward, "<f4", (b,)).copy(),
        "intrinsic": wire.array(r.intrinsic, "<f4", (b,)).copy(),
        "discount": wire.array(r.discount, "<f4", (b,)).copy(),
        "index": wire.array(r.index, "<i8", (b,)).copy(),
        "policy_version": wire.array(r.policy_version, "<i8", (b,)).copy(),
    }


class ZenohReplayClient:
    """The replay service seen from the learner. Thread-safe: prefetch threads share one.

    A failed or malformed reply is logged (rate limited) and counted in `invalid`, and
    the call returns None: the caller asks again.
    """

    def __init__(self, session, keys: wire.Keys, spec: EnvSpec, log: Log, timeout_s: float = 30.0,
                 steps: int | None = None) -> None:
        self.session = session
        self.keys = keys
        self.spec = spec
        self.bounds = wire.Bounds.of(spec, steps=steps)  # `steps`: the run's budget, bounding counts
        self.log = log
        self.timeout_s = timeout_s
        self.invalid = 0
        self._num_inserted = 0
        self._lock = threading.Lock()

    @property
    def num_inserted(self) -> int:
        return self._num_inserted

    def _seen(self, num_inserted: int) -> None:
        with self._lock:
            self._num_inserted = max(self._num_inserted, num_inserted)

    def _invalid(self, what: str) -> None:
        with self._lock:
            self.invalid += 1
        self.log.every("replay-invalid", 5.0, f"invalid replay reply ({self.invalid} so far): {what}")

    def _ask(self, key: str, request: wire.Message, timeout_s: float) -> wire.SampleReply | None:
        """The replay's answer to one request; None if nobody answered or the answer was bad."""
        import zenoh

        try:
            replies = self.session.get(
                key, payload=wire.encode(request), timeout=timeout_s,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            answer = None
            for reply in replies:
                if reply.ok is None:
                    self._invalid(f"{key}: error reply {reply.err.payload.to_bytes()!r}")
                    continue
                answer = wire.decode(reply.ok.payload.to_bytes(), wire.SampleReply, self.bounds)
                self._seen(answer.num_inserted)
            return answer
        except wire.WireError as err:
            self._invalid(f"{key}: {err}")
        except zenoh.ZError as err:
            self.log.every("replay-get", 5.0, f"request on {key} failed: {err}")
        except Exception as err:  # noqa: BLE001 -- a reply never kills a prefetch thread
            self._invalid(f"{key}: {err}")
        return None

    def sample(self, batch_size: int, wait_s: float) -> Batch | None:
        reply = self._ask(self.keys.sample, wire.SampleRequest(batch_size, wait_s), self.timeout_s)
        if reply is None:
            time.sleep(min(wait_s, 0.2))  # no replay (yet): do not spin
            return None
        return self._decode(reply)

    def sync_samples(self, updates: int) -> bool:
        """Tell the replay's rate limiter how many samples this learner has used (its update count at
        start): the samples a dead learner drew after its checkpoint are drawn again. True once done."""
        request = wire.SampleRequest(1, 0.0, sync_samples=updates)
        reply = self._ask(self.keys.sample, request, min(self.timeout_s, 10.0))
        return reply is not None and reply.reason == "synced"

    def unscored(self, after: int, limit: int) -> tuple[Batch | None, int]:
        reply = self._ask(self.keys.unscored, wire.UnscoredRequest(after, limit), min(self.timeout_s, 10.0))
        if reply is None:
            return None, after  # nothing learnt: claim nothing scored
        return self._decode(reply), reply.num_inserted

    def _decode(self, reply: wire.SampleReply) -> Batch | None:
        if not reply.ok:
            return None
        try:
            return decode_reply(reply, self.spec)
        except wire.WireError as err:
            self._invalid(f"batch: {err}")
            return None

    def set_intrinsic(self, index: np.ndarray, values: np.ndarray) -> None:
        import zenoh

        index, values = np.asarray(index, "<i8"), np.asarray(values, "<f4")
        block = zenoh.CongestionControl.BLOCK
        # The replay refuses a message of more than MAX_BATCH scores (the warm-up's zeros can be more).
        for start in range(0, len(index), wire.MAX_BATCH):
            part = slice(start, start + wire.MAX_BATCH)
            msg = wire.SetIntrinsic(index[part].tobytes(), values[part].tobytes())
            self.session.put(self.keys.intrinsic, wire.encode(msg), congestion_control=block)


# -- prefetching -----------------------------------------------------------------------------


class Prefetcher:
    """`threads` threads, each keeping one sample request in flight, feeding a queue of that size.

    Use as a context manager: it starts the threads, and on exit stops and joins them. `misses`
    counts requests answered with no batch; `last_miss` is when the latest one came
    (time.monotonic()), so the caller can tell that the replay ran dry after it was done.
    `drawn` counts the batches the replay served, from the moment each reply arrives: a caller
    that counts the batches it took knows exactly how many the replay has counted that it has
    not used yet, wherever they wait (see `paused`).
    """

    def __init__(self, client: ReplayClient, batch_size: int, threads: int, stop: StopFlag,
                 wait_s: float = 1.0) -> None:
        self.client = client
        self.batch_size = batch_size
        self.stop = stop
        self.wait_s = wait_s
        self.misses = 0
        self.last_miss: float | None = None
        self.drawn = 0
        self._closed = threading.Event()
        self._state = threading.Condition()
        self._paused = False
        self._in_flight = 0
        self._queue: queue.Queue[Batch] = queue.Queue(maxsize=max(1, threads))
        self._threads = [threading.Thread(target=self._loop, name=f"prefetch{i}", daemon=True)
                         for i in range(max(1, threads))]

    def __enter__(self) -> Prefetcher:
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._closed.set()
        for t in self._threads:
            t.join(timeout=5.0)

    def get(self, timeout: float) -> Batch | None:
        """The next batch, or None if none came within timeout."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def _running(self) -> bool:
        return not self.stop and not self._closed.is_set()

    def dead(self) -> list[str]:
        """Names of prefetch threads that ended while the prefetcher runs (none should)."""
        if not self._running():
            return []
        return [t.name for t in self._threads if t.ident is not None and not t.is_alive()]

    @contextmanager
    def paused(self, timeout: float) -> Iterator[bool]:
        """No new request is sent inside the block. Yields True once every request in flight has
        been answered (so `drawn` is final until the block ends), False if some still were after
        `timeout` seconds."""
        with self._state:
            self._paused = True
            quiet = self._state.wait_for(lambda: self._in_flight == 0, timeout)
        try:
            yield quiet
        finally:
            with self._state:
                self._paused = False
                self._state.notify_all()

    def _loop(self) -> None:
        while self._running():
            with self._state:
                while self._paused and self._running():
                    self._state.wait(0.2)
                self._in_flight += 1
            batch = None
            try:
                batch = self.client.sample(self.batch_size, self.wait_s)
            finally:
                with self._state:
                    self._in_flight -= 1
                    self.drawn += batch is not None
                    self._state.notify_all()
            if batch is None:
                self.misses += 1
                self.last_miss = time.monotonic()
                continue
            while self._running():
                try:
                    self._queue.put(batch, timeout=0.2)
                    break
                except queue.Full:
                    continue
