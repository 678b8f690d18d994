"""The replay store behind Zenoh: inserts from actors, batches for the learner, stats.

- Inserts: actors publish `TransitionBatch`es (BLOCK). The subscriber callback
  only queues the bytes; one insert thread decodes, waits on the rate limiter,
  adds to the store, and acknowledges each batch (`InsertAck`). Actors keep a
  bounded number of unacknowledged batches, so when the limiter holds inserts
  back the actors wait: that is the backpressure.
- Episodes are stitched by (actor_id, incarnation, episode, step): a batch that
  does not continue its episode exactly (an actor restarted, a batch was lost,
  this service restarted) is dropped, counted, and its episode ignored until
  the actor begins a new one. A restarted actor has a new incarnation, so its
  half episode is never stitched to a new one.
- Sampling: a queryable on `replay/sample`; sampler threads wait on the limiter
  (up to the request's wait_s, else reply ok=False) and reply with the batch.
  The learner keeps several requests in flight, so it is never left waiting.
- Intrinsic rewards: transitions of the global warm-up (index < warmup_steps)
  are stored with intrinsic 0, as the reference does; later ones unscored
  (NaN) until the learner writes their score back (`replay/intrinsic`).
- Rate limit: `SampleToInsertRatio` with samples_per_insert = G (one sample =
  one batch = one update), min size warmup_steps + 1 (the trainer's first
  update follows step warmup + 1). On restart its counts are set from the
  store: inserts = num_inserted, samples = G * (num_inserted - warmup).
- Persistence: the store logs every add in its data directory and is
  snapshotted every `snapshot_every` inserts; the run's step budget
  (config.steps) caps inserts.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from shared import wire
from shared.replay.rate_limiter import RateLimiterClosed, SampleToInsertRatio
from shared.replay.store import ReplayStore
from shared.service import Log, StopFlag
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK
MAX_BATCH = 4096


@dataclass
class ReplayArgs(ServiceArgs):
    """The replay service: stores transitions from actors and serves batches to the learner."""

    data: Path = field(default_factory=lambda: Path(os.environ.get("NASA_DATA", "runs/default")))
    """Run folder; the store lives in <data>/replay (env NASA_DATA)."""
    error_buffer: float = 0.0
    """Rate limiter tolerance in samples; 0: 2 * G * 16 + 8 (two 8-transition batches of two actors)."""
    no_rate_limit: bool = False
    """Benchmarks only: sample and insert without the samples-per-insert ratio."""
    sample_threads: int = 2
    stats_every_s: float = 0.5
    snapshot_every: int = 50_000
    """Compact the store's log every this many inserts."""


def default_error_buffer(updates_per_step: int) -> float:
    return 2.0 * updates_per_step * 16 + 8


class ReplayService:
    def __init__(self, args: ReplayArgs, session: zenoh.Session, stop: StopFlag, action_dim: int) -> None:
        c = args.config
        self.args = args
        self.config = c
        self.session = session
        self.stop = stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("replay")
        self.frame_shape = (3, c.env.image_size, c.env.image_size)
        self.action_dim = action_dim
        self.store = ReplayStore(
            capacity=c.replay_capacity,
            frame_shape=self.frame_shape,
            frame_stack=c.env.frame_stack,
            action_dim=action_dim,
            data_dir=Path(args.data) / "replay",
            compression=c.replay_compression,
        )
        g = c.updates_per_step
        self.limiter: SampleToInsertRatio | None = None
        if not args.no_rate_limit:
            eb = args.error_buffer or default_error_buffer(g)
            self.limiter = SampleToInsertRatio(g, c.warmup_steps + 1, eb)
            n = self.store.num_inserted
            self.limiter.inserts = n
            self.limiter.samples = g * max(0, n - c.warmup_steps)
        self.invalid = 0
        self.dropped = 0
        self.samples_served = 0
        # (actor, incarnation) -> [episode, store episode id, next step]
        self._episodes: dict[tuple[int, int], list[int]] = {}
        self._inserts: queue.Queue[bytes] = queue.Queue()
        self._queries: queue.Queue[tuple[zenoh.Query, wire.SampleRequest]] = queue.Queue()
        self._scoring_queries: queue.Queue[tuple[zenoh.Query, wire.SampleRequest]] = queue.Queue()
        self._last_snapshot = self.store.num_inserted
        self._threads: list[threading.Thread] = []
        if self.store.num_inserted:
            self.log(f"reopened {args.data}/replay with {self.store.num_inserted} transitions")

    # -- Zenoh callbacks: queue and return --------------------------------------------

    def _on_insert(self, sample: zenoh.Sample) -> None:
        self._inserts.put(sample.payload.to_bytes())

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            payload = query.payload
            req = wire.decode(payload.to_bytes() if payload is not None else b"", wire.SampleRequest)
        except wire.WireError as err:
            self._reject(query, err)
            query.drop()
            return
        # Scoring requests get their own thread: training requests may wait on the rate limiter.
        (self._scoring_queries if req.unscored_after >= 0 else self._queries).put((query, req))

    def _on_intrinsic(self, sample: zenoh.Sample) -> None:
        try:
            msg = wire.decode(sample.payload.to_bytes(), wire.SetIntrinsic)
            index = np.frombuffer(msg.index, "<i8")
            value = wire.array(msg.value, "<f4", index.shape)
            self.store.set_intrinsic(index, value)
        except (wire.WireError, ValueError) as err:
            self._invalid(f"set_intrinsic: {err}")
        except RuntimeError:  # store closed during shutdown
            pass

    def _on_stop(self, sample: zenoh.Sample) -> None:
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except wire.WireError as err:
            self._invalid(f"stop: {err}")

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def _reject(self, query: zenoh.Query, err: wire.WireError) -> None:
        """Counts and answers a bad sample request (a malformed message or impossible values)."""
        self._invalid(f"sample request: {err}")
        query.reply_err(str(err).encode())

    # -- inserts ------------------------------------------------------------------------

    def _insert_loop(self) -> None:
        while not self.stop:
            try:
                payload = self._inserts.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                msg = wire.decode(payload, wire.TransitionBatch)
                accepted = self.insert_batch(msg)
            except (wire.WireError, ValueError) as err:
                self._invalid(f"transitions: {err}")
                continue
            except RateLimiterClosed:
                return
            ack = wire.InsertAck(msg.actor_id, msg.incarnation, msg.seq, accepted, self.store.num_inserted)
            self.session.put(self.keys.ack(msg.actor_id), wire.encode(ack), congestion_control=BLOCK)

    def insert_batch(self, msg: wire.TransitionBatch) -> int:
        """Add a batch's transitions; returns how many were stored. ValueError if malformed."""
        n, a = msg.n, self.action_dim
        if not 1 <= n <= MAX_BATCH:
            raise wire.WireError(f"batch of {n} transitions")
        if tuple(msg.frame_shape) != self.frame_shape:
            raise wire.WireError(f"frame shape {msg.frame_shape}, this run stores {self.frame_shape}")
        frames = wire.decode_frames(msg.frames, n, self.frame_shape)
        actions = wire.array(msg.actions, "<f4", (n, a))
        rewards = wire.array(msg.rewards, "<f4", (n,))
        discounts = wire.array(msg.discounts, "<f4", (n,))
        lasts = wire.array(msg.lasts, "u1", (n,))
        versions = wire.array(msg.policy_versions, "<i8", (n,))
        key = (msg.actor_id, msg.incarnation)
        if msg.start == 0:
            if msg.first_frame is None:
                raise wire.WireError("an episode's first batch must carry its first frame")
            first = wire.decode_frames(msg.first_frame, 1, self.frame_shape)[0]
            store_id = self.store.begin_episode(first, msg.actor_id, msg.incarnation)
            self._episodes[key] = [msg.episode, store_id, 0]
        entry = self._episodes.get(key)
        if entry is None or entry[0] != msg.episode or entry[2] != msg.start:
            # Not a continuation of a known episode: never stitch, drop until the next episode.
            self.dropped += n
            self.log.every("orphan", 5.0, f"dropped {n} transitions of actor {key} episode {msg.episode}")
            return 0
        c = self.config
        accepted = 0
        for i in range(n):
            if self.store.num_inserted >= c.steps:
                self.dropped += n - i
                break
            if self.limiter is not None:
                while not self.limiter.await_insert(timeout=0.5):
                    if self.stop:
                        raise RateLimiterClosed("stopping")
            g = self.store.num_inserted
            intrinsic = 0.0 if g < c.warmup_steps else math.nan
            last = bool(lasts[i])
            self.store.add(
                entry[1], actions[i], float(rewards[i]), float(discounts[i]), frames[i], last,
                policy_version=int(versions[i]), intrinsic=intrinsic,
            )
            if self.limiter is not None:
                self.limiter.insert()
            entry[2] += 1
            accepted += 1
            if last:
                del self._episodes[key]
                break
        return accepted

    # -- sampling -----------------------------------------------------------------------

    def _sample_loop(self, seed: int, queries: queue.Queue[tuple[zenoh.Query, wire.SampleRequest]]) -> None:
        rng = np.random.default_rng(seed)
        while not self.stop:
            try:
                query, req = queries.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                reply = self.sample(req, rng)
                query.reply(self.keys.sample, wire.encode(reply))
            except wire.WireError as err:
                self._reject(query, err)
            except RateLimiterClosed:
                query.reply_err(b"replay stopping")
            finally:
                query.drop()

    def sample(self, req: wire.SampleRequest, rng: np.random.Generator) -> wire.SampleReply:
        if not 1 <= req.batch_size <= MAX_BATCH:
            raise wire.WireError(f"batch_size {req.batch_size}")
        if req.unscored_after >= 0:
            return self.unscored(req)
        wait = min(max(float(req.wait_s), 0.0), 10.0)
        if self.limiter is not None:
            if not self.limiter.await_sample(1, timeout=wait):
                return wire.SampleReply(False, "rate limited", self.store.num_inserted)
            self.limiter.sample(1)
        elif len(self.store) == 0:
            time.sleep(min(wait, 0.2))
            return wire.SampleReply(False, "empty", self.store.num_inserted)
        b = self.store.sample(req.batch_size, rng)
        self.samples_served += 1
        return self._reply(b)

    def unscored(self, req: wire.SampleRequest) -> wire.SampleReply:
        """The oldest unscored transitions from req.unscored_after on, for the learner to score
        soon after they are stored (collect timing). Not a training sample: not rate limited."""
        n = self.store.num_inserted  # read first: anything newer is past the scan
        index = self.store.unscored(req.unscored_after, req.batch_size)
        if len(index) == 0:
            return wire.SampleReply(False, "none unscored", n)
        return self._reply(self.store.get(index))

    def _reply(self, b: dict[str, np.ndarray]) -> wire.SampleReply:
        window = b["window"]
        return wire.SampleReply(
            ok=True,
            reason="",
            num_inserted=self.store.num_inserted,
            batch_size=len(window),
            window_shape=list(window.shape),
            window=window.tobytes(),
            action=b["action"].astype("<f4").tobytes(),
            reward=b["reward"].astype("<f4").tobytes(),
            intrinsic=b["intrinsic"].astype("<f4").tobytes(),
            discount=b["discount"].astype("<f4").tobytes(),
            index=b["index"].astype("<i8").tobytes(),
            policy_version=b["policy_version"].astype("<i8").tobytes(),
        )

    # -- stats and lifetime ------------------------------------------------------------

    def stats(self) -> wire.ReplayStats:
        s = self.store.stats()
        lim = self.limiter.stats() if self.limiter is not None else {"inserts": 0, "samples": 0}
        return wire.ReplayStats(
            size=s["size"],
            bytes=int(s["bytes_in_ram"]),
            num_inserted=s["num_inserted"],
            inserts=int(lim["inserts"]),
            samples=int(lim["samples"]),
            invalid=self.invalid,
            dropped=self.dropped,
            done=s["num_inserted"] >= self.config.steps,
        )

    def run(self) -> None:
        s, k = self.session, self.keys
        with (
            s.declare_subscriber(k.insert_all, self._on_insert),
            s.declare_subscriber(k.intrinsic, self._on_intrinsic),
            s.declare_subscriber(k.stop, self._on_stop),
            s.declare_queryable(k.sample, self._on_query),
            s.liveliness().declare_token(k.alive("replay", 0)),
        ):
            self._threads = [threading.Thread(target=self._insert_loop, name="insert", daemon=True)]
            for i in range(max(1, self.args.sample_threads)):
                seed = self.config.seed * 1000 + self.store.num_inserted + i
                self._threads.append(threading.Thread(
                    target=self._sample_loop, args=(seed, self._queries), name=f"sample{i}", daemon=True
                ))
            self._threads.append(threading.Thread(
                target=self._sample_loop, args=(0, self._scoring_queries), name="unscored", daemon=True
            ))
            for t in self._threads:
                t.start()
            n, budget = self.store.num_inserted, self.config.steps
            self.log(f"serving run {k.run_id}: {n} transitions, budget {budget}")
            while not self.stop.wait(self.args.stats_every_s):
                s.put(k.replay_stats, wire.encode(self.stats()))
                if self.store.num_inserted - self._last_snapshot >= self.args.snapshot_every:
                    self._last_snapshot = self.store.num_inserted
                    self.store.snapshot(block=False)
            self.log(f"stopping ({self.stop.reason})")
            if self.limiter is not None:
                self.limiter.close()
            for t in self._threads:
                t.join(timeout=5.0)
            s.put(k.replay_stats, wire.encode(self.stats()))
        self.store.flush()
        self.store.close()


def main(argv: list[str] | None = None) -> None:
    from shared import envs
    from shared.service import run_service

    def run(args: ReplayArgs, session: zenoh.Session, stop: StopFlag) -> None:
        ReplayService(args, session, stop, envs.from_config(args.config.env, 0).action_dim).run()

    run_service(ReplayArgs, argv, "python -m services.replay", run)
