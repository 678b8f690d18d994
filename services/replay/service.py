"""The replay store behind Zenoh: inserts from actors, batches for the learner, stats.

- Config: the run folder's config.json (shared.run_config.open_folder) gives
  the EnvSpec (frame shape, frame stack, action size): the replay builds no
  environment. It serves that RunConfig on `replay/config`, so every other
  service of the run checks its own settings against it.
- Inserts: actors publish `TransitionBatch`es (BLOCK). The subscriber callback
  decodes and checks each batch and queues it; one insert thread waits on the
  rate limiter, adds to the store, and acknowledges each batch (`InsertAck`), a refused one
  with the reason and whether it holds for the actor's every later batch (an
  incarnation older than one seen, an id the store cannot keep, frames not of
  the run's shape: that actor stops); a batch that does not decode is
  answered from the callback, where it names its actor and incarnation.
  Actors keep a bounded number of unacknowledged batches
  (shared.replay.adder.ZenohWriter), so when the limiter holds inserts back
  the actors wait: that is the backpressure.
- Episodes are stitched by (actor_id, incarnation, episode, step): a batch that
  does not continue its episode exactly (an actor restarted, a batch was lost,
  this service restarted) is dropped, counted, and its episode ignored until
  the actor begins a new one. A restarted actor has a new incarnation, so its
  half episode is never stitched to a new one. One open episode is held per
  actor id, and those the store has closed are forgotten (an actor id gone for
  good: shared/replay/README.md), so restarts leave nothing behind.
- Sampling: a queryable on `replay/sample`; sampler threads wait on the limiter
  (up to the request's wait_s, else reply ok=False) and reply with the batch,
  with or without replacement (config.sample_without_replacement).
- Intrinsic rewards: every row is stored unscored (NaN); the learner's scorer
  asks for the oldest unscored rows on `replay/unscored` (served on its own
  thread, outside the rate limiter: not a training sample) and writes the
  scores back on `replay/intrinsic`.
- Rate limit: `SampleToInsertRatio` with samples_per_insert = G (one sample =
  one batch = one update), min size warmup_steps + 1 (the trainer's first
  update follows step warmup + 1; warmup_steps with --updates-before-store,
  whose first update comes before that step's transition is stored:
  shared.schedule.first_update_rows), and with --warmup-burst the burst's
  updates beyond G allowed at once after it (shared.schedule.limiter_extra). On restart its counts are
  restored from the store: inserts = num_inserted, samples = the updates the
  schedule makes on that many transitions (shared.schedule.stored_updates).
- Persistence: the store logs every add in its data directory and is
  snapshotted every `snapshot_every` inserts; the run's step budget
  (config.steps) caps inserts.
- One replay per run: before serving it looks for the run's replay token and
  exits 2 if another process holds it (shared.faults.claim_role).
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np
import zenoh

from shared import envs, faults, run_config, wire
from shared.config import ConfigError
from shared.replay.client import LocalReplay, encode_reply
from shared.replay.log import MANIFEST
from shared.replay.rate_limiter import RateLimiterClosed, SampleToInsertRatio
from shared.replay.store import SNAPSHOT_EVERY, ActorRefused, OpenStopped, open_store
from shared.run_config import RunConfig
from shared.schedule import first_update_rows, limiter_extra, stored_updates
from shared.service import Log, MessageGuard, StopFlag
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK
MAX_BATCH = 4096
WRITE_RETRY_S = 1.0
FORGET_EVERY = 1024
"""Actor ids with an open episode the service holds before it forgets those the store has closed."""


@dataclass
class ReplayArgs(ServiceArgs):
    """The replay service: stores transitions from actors and serves batches to the learner."""

    data: Path = field(default_factory=lambda: Path(os.environ.get("NASA_DATA", "runs/default")))
    """Run folder: config.json, and the store in <data>/replay (env NASA_DATA)."""
    error_buffer: float = 0.0
    """Rate limiter tolerance in samples; 0: 2 * G * 16 + 8 (two 8-transition batches of two actors)."""
    no_rate_limit: bool = False
    """Benchmarks only: sample and insert without the samples-per-insert ratio."""
    sample_threads: int = 2
    stats_every_s: float = 0.5
    snapshot_every: int = SNAPSHOT_EVERY
    """Compact the store's log every this many inserts."""
    camera_checked: bool = False
    """Set by `nasa up`, which has checked the run's camera against the task's model before starting
    anything: the replay does not load the model again at each start. A replay started alone checks it."""
    max_abs_reward: float = wire.Bounds.max_abs_reward
    """Refuse transitions whose reward is beyond +-this (a huge finite reward poisons the critic);
    at most the wire's bound, which the learner applies to the batches it samples. Intrinsic scores
    are held to the wire's bound, to which the learner clips them."""


def check_args(args: ReplayArgs) -> None:
    """The replay's flags that its parser cannot check (ConfigError: exit 2 before it connects)."""
    if not (math.isfinite(args.stats_every_s) and args.stats_every_s > 0):
        raise ConfigError(f"--stats-every-s must be a finite number > 0, got {args.stats_every_s}")
    # The learner refuses batches holding rewards beyond the wire's bound: this one can only be tighter.
    if not 0 < args.max_abs_reward <= wire.Bounds.max_abs_reward:
        raise ConfigError(f"--max-abs-reward must be > 0 and at most {wire.Bounds.max_abs_reward:g} (what "
                          f"the learner accepts), got {args.max_abs_reward}")
    if not (math.isfinite(args.error_buffer) and args.error_buffer >= 0):
        raise ConfigError(
            f"--error-buffer must be a finite number >= 0 (0: the default), got {args.error_buffer}")
    for name in ("snapshot_every", "sample_threads"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    # The replay's config is the run's (every other service joins it): its camera must exist before
    # any actor renders with it.
    if not args.camera_checked:
        envs.check_camera(args.config.env)


def default_error_buffer(updates_per_step: int) -> float:
    return 2.0 * updates_per_step * 16 + 8


class ReplayService(MessageGuard):
    def __init__(self, args: ReplayArgs, session: zenoh.Session, stop: StopFlag, run: RunConfig) -> None:
        c = run.config
        self.args, self.run_config, self.config = args, run, c
        self.session = session
        self.stop = stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("replay")
        self.frame_shape = run.spec.frame_shape
        self.action_dim = run.spec.action_dim
        self.bounds = wire.Bounds.of(run.spec, args.max_abs_reward)
        # Scores are the learner's own, clipped by its scorer to the wire's bound: held to a lower
        # --max-abs-reward, a batch of them was refused, its rows stayed unscored, and every batch
        # that drew them sent the refused scores again (each counted invalid).
        self.score_bounds = wire.Bounds.of(run.spec)
        folder = Path(args.data) / "replay"
        if (folder / MANIFEST).exists():
            self.log(f"reopening {folder}: reading its log (a stop signal ends the reading, losing nothing)")
        # A long log takes a while to read: a stop signal meanwhile ends it (OpenStopped).
        self.store = open_store(run, folder, stop=stop.event.is_set)
        self.limiter: SampleToInsertRatio | None = None
        if not args.no_rate_limit:
            g = c.updates_per_step
            error_buffer = args.error_buffer or default_error_buffer(g)
            self.limiter = SampleToInsertRatio(g, first_update_rows(c), error_buffer, limiter_extra(c))
            n = self.store.num_inserted
            self.limiter.restore(inserts=n, samples=stored_updates(n, c))
        self.replace = not c.sample_without_replacement
        # Sampling through the client's in-process side; each sampler thread has its own rng.
        self.local = LocalReplay(self.store, np.random.default_rng(0), self.limiter, self.replace)
        self.dropped = 0
        self.write_error = ""  # why the log cannot be written now ("" when it can)
        self.samples_served = 0
        # (actor, incarnation) -> [episode, store episode id, next step]
        # actor id -> [incarnation, episode, store episode id, next start] of its open episode. Keyed by
        # the id alone: a restarted actor's new incarnation replaces the entry (the store closes the
        # old episode too), so restarts in the middle of an episode leave nothing behind.
        self._episodes: dict[int, list[int]] = {}
        # actor id -> (incarnation, launch) of the launch that holds it: of two launches of one id that
        # got one incarnation, the first heard keeps it (one entry per id, as the store's incarnations).
        self._launches: dict[int, tuple[int, int]] = {}
        self._forget_at = FORGET_EVERY
        self._inserts: queue.Queue[wire.TransitionBatch] = queue.Queue()
        self._queries: queue.Queue[tuple[zenoh.Query, wire.SampleRequest]] = queue.Queue()
        self._unscored: queue.Queue[tuple[zenoh.Query, wire.UnscoredRequest]] = queue.Queue()
        self._threads: list[threading.Thread] = []
        if self.store.num_inserted:
            self.log(f"reopened {args.data}/replay with {self.store.num_inserted} transitions")

    # -- Zenoh callbacks: queue and return --------------------------------------------

    def _on_insert(self, sample: zenoh.Sample) -> None:
        # Checked here, before the batch queues behind the rate limiter: a bad one is refused at once.
        try:
            self._inserts.put(wire.decode(sample.payload.to_bytes(), wire.TransitionBatch, self.bounds))
        except Exception as err:  # noqa: BLE001 -- a message never kills a callback
            self._invalid(f"transitions: {err}")
            self._refuse_undecoded(sample, err)

    def _refuse_undecoded(self, sample: zenoh.Sample, err: Exception) -> None:
        """Acknowledge a batch that does not decode, where it names its actor (as its key does) and
        incarnation: else that actor waited on it. Lasting where its frames are not of the run's
        shape, which no later batch of that actor's will be either. Not BLOCK: a callback must not
        wait on the network (a refusal dropped there is one the actor counts lost after a while)."""
        try:
            body = msgpack.unpackb(sample.payload.to_bytes(), raw=False, strict_map_key=False)
            actor_id, incarnation, shape = body["actor_id"], body["incarnation"], body.get("frame_shape")
            named = wire.is_count(actor_id) and wire.is_count(incarnation)
            if not named or str(sample.key_expr) != self.keys.insert(actor_id):
                return
            lasting = isinstance(shape, list) and shape != list(self.frame_shape)
            # Echoed only where a writer can read it back (an ack it refuses never reaches it); 0 is
            # taken by every launch of the incarnation.
            launch = body.get("launch", 0)
            launch = launch if wire.is_count(launch) else 0
            ack = wire.InsertAck(actor_id, incarnation, self.store.num_inserted, str(err)[:wire.MAX_TEXT],
                                 lasting, launch)
            self.session.put(self.keys.ack(actor_id), wire.encode(ack))
        except Exception:  # noqa: BLE001 -- not msgpack, not a map, no such fields: nobody to answer
            return

    def _on_sample_query(self, query: zenoh.Query) -> None:
        self._queue_query(query, wire.SampleRequest, self._queries)

    def _on_unscored_query(self, query: zenoh.Query) -> None:
        self._queue_query(query, wire.UnscoredRequest, self._unscored)

    def _queue_query(self, query: zenoh.Query, cls: type[wire.Message], into: queue.Queue) -> None:
        try:
            payload = query.payload
            req = wire.decode(payload.to_bytes() if payload is not None else b"", cls, self.bounds)
        except wire.WireError as err:
            self._reject(query, err)
            query.drop()
            return
        into.put((query, req))

    def _on_intrinsic(self, sample: zenoh.Sample) -> None:
        try:
            msg = wire.decode(sample.payload.to_bytes(), wire.SetIntrinsic, self.score_bounds)
            index = np.frombuffer(msg.index, "<i8")
            value = wire.array(msg.value, "<f4", index.shape)
            self.store.set_intrinsic(index, value)
        except RuntimeError:  # store closed during shutdown
            pass
        except OSError as err:  # a full disk: the score is lost, the learner scores the row when sampled
            self.write_error = f"{type(err).__name__}: {err}"
        except Exception as err:  # noqa: BLE001 -- out-of-range indices (ValueError) and the unforeseen
            self._invalid(f"set_intrinsic: {err}")

    def _reject(self, query: zenoh.Query, err: Exception) -> None:
        """Counts and answers a bad request (a malformed message or impossible values)."""
        self._invalid(f"request on {query.key_expr}: {err}")
        try:
            query.reply_err(str(err).encode())
        except Exception as reply_err:  # noqa: BLE001 -- the querier may be gone
            self.log.every("reply", 5.0, f"could not answer a bad request: {reply_err}")

    # -- inserts ------------------------------------------------------------------------

    def _insert_loop(self) -> None:
        while not self.stop:
            try:
                msg = self._inserts.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                refused, lasting = self._take(msg)
            except RateLimiterClosed:
                return
            # Refused batches are acknowledged too, saying why: the actor must not wait on them, and
            # one whose every batch is refused stops instead of acting for nothing.
            ack = wire.InsertAck(msg.actor_id, msg.incarnation, self.store.num_inserted,
                                 refused[:wire.MAX_TEXT], lasting, msg.launch)
            self.session.put(self.keys.ack(msg.actor_id), wire.encode(ack), congestion_control=BLOCK)

    def _take(self, msg: wire.TransitionBatch) -> tuple[str, bool]:
        """Insert a batch: (why it was refused, "" if it was stored; whether every later batch of its
        incarnation will be refused for the same reason)."""
        try:
            if self.insert_batch(msg):
                return "", False
        except ActorRefused as err:
            self._invalid(f"transitions: {err}")
            return str(err), True
        except RateLimiterClosed:
            raise
        except Exception as err:  # noqa: BLE001 -- ValueError from the store, and the unforeseen
            self._invalid(f"transitions: {err}")
            return str(err), False
        if self.store.num_inserted >= self.config.steps:
            return "the run's step budget is reached", False
        # One reason for all of them: the actor logs each reason once.
        return "not the continuation of an episode begun here", False

    def _check_launch(self, msg: wire.TransitionBatch) -> None:
        """ActorRefused for a launch of an id whose incarnation another launch holds (two hosts that
        started it in the same tenth of a second): their streams must not be taken for one."""
        held = self._launches.get(msg.actor_id)
        if held is not None and held[0] == msg.incarnation and held[1] != msg.launch:
            raise ActorRefused(
                f"actor {msg.actor_id} incarnation {msg.incarnation} is another launch's: this id was "
                "started twice at the same moment; give each actor its own --actor-id")
        if held is None or msg.incarnation > held[0]:
            self._launches[msg.actor_id] = (msg.incarnation, msg.launch)

    def insert_batch(self, msg: wire.TransitionBatch) -> int:
        """Add a batch's transitions, unscored; returns how many were stored. The batch was decoded
        with this run's bounds (wire.check_transitions), so its arrays fit the store."""
        n, arrays = msg.n, getattr(msg, "arrays", None)
        if arrays is None:  # built in process rather than decoded: check it the same way
            arrays = wire.decode(wire.encode(msg), wire.TransitionBatch, self.bounds).arrays
        frames, actions, rewards = arrays["frames"], arrays["action"], arrays["reward"]
        discounts, lasts, versions = arrays["discount"], arrays["last"], arrays["policy_version"]
        key = msg.actor_id
        self._check_launch(msg)
        if self.store.num_inserted >= self.config.steps:
            self.dropped += n  # past the step budget: the actors stop once they hear of it
            return 0
        if msg.start == 0:
            first = arrays["first_frame"]
            store_id = self._durably(lambda: self.store.begin_episode(first, msg.actor_id, msg.incarnation))
            self._episodes[key] = [msg.incarnation, msg.episode, store_id, 0]
            if len(self._episodes) >= self._forget_at:
                self._forget_closed()
        entry = self._episodes.get(key)
        if entry is not None and not self.store.is_open(entry[2]):
            # The store closed it: nothing came for a whole capacity of inserts (store.py).
            del self._episodes[key]
            entry = None
        if entry is None or entry[:2] != [msg.incarnation, msg.episode] or entry[3] != msg.start:
            # Not a continuation of a known episode: never stitch, drop until the next episode.
            self.dropped += n
            self.log.every("orphan", 5.0, f"dropped {n} transitions of actor {(key, msg.incarnation)} "
                                          f"episode {msg.episode}")
            return 0
        accepted = 0
        for i in range(n):
            if self.store.num_inserted >= self.config.steps:
                self.dropped += n - i
                break
            if self.limiter is not None:
                while not self.limiter.await_insert(timeout=0.5):
                    if self.stop:
                        raise RateLimiterClosed("stopping")
            last = bool(lasts[i])
            self._durably(lambda i=i, last=last: self.store.add(
                entry[2], actions[i], float(rewards[i]), float(discounts[i]), frames[i], last,
                policy_version=int(versions[i]),
            ))
            if self.limiter is not None:
                self.limiter.insert()
            entry[3] += 1
            accepted += 1
            if last:
                del self._episodes[key]
                break
        return accepted

    def _forget_closed(self) -> None:
        """Drop the entries of episodes the store has closed: replicas that take a new id at each
        start leave one each, never continued. Once the entries double, so the scans cost O(1) an
        episode, and the entries stay within twice the actors still sending."""
        self._episodes = {a: e for a, e in self._episodes.items() if self.store.is_open(e[2])}
        self._forget_at = max(FORGET_EVERY, 2 * len(self._episodes))

    def _durably(self, write):  # noqa: ANN001, ANN202
        """write() once the log takes it: a failed write (a full disk) is never acknowledged; the
        insert thread stops taking batches (the actors wait on their acknowledgements), the stats
        say why, and it resumes by itself when the write succeeds (the log cut the torn record)."""
        while True:
            try:
                result = write()
            except OSError as err:
                if not self.write_error:
                    self.log(f"cannot write the log, inserts paused: {err}")
                self.write_error = f"{type(err).__name__}: {err}"
                if self.stop.wait(WRITE_RETRY_S):
                    raise RateLimiterClosed("stopping") from err
                continue
            if self.write_error:
                self.log("the log takes writes again: inserts resume")
                self.write_error = ""
            return result

    # -- sampling -----------------------------------------------------------------------

    def _serve_loop(self, queries: queue.Queue, answer) -> None:  # noqa: ANN001
        """Answer the queued queries of one kind, one at a time (answer(request) -> SampleReply)."""
        while not self.stop:
            try:
                query, req = queries.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                query.reply(query.key_expr, wire.encode(answer(req)))
            except RateLimiterClosed:
                query.reply_err(b"replay stopping")
            except Exception as err:  # noqa: BLE001 -- a request never kills a serving thread
                self._reject(query, err)
            finally:
                query.drop()

    def sampler(self, seed: int):  # noqa: ANN201 (request -> reply)
        """The answer function of one sampler thread: its own rng over the shared store and limiter."""
        local = LocalReplay(self.store, np.random.default_rng(seed), self.limiter, self.replace)
        return lambda req: self.sample(req, local)

    def sample(self, req: wire.SampleRequest, local: LocalReplay | None = None) -> wire.SampleReply:
        """A training batch (paced by the rate limiter), or ok=False after up to req.wait_s."""
        if not 1 <= req.batch_size <= MAX_BATCH:
            raise wire.WireError(f"batch_size {req.batch_size}")
        if req.sync_samples is not None:  # a learner's start: count the samples it has used
            if self.limiter is not None:
                counted = self.limiter.stats()["samples"]
                self.limiter.lower_samples(req.sync_samples)
                self.log(f"a learner has used {req.sync_samples} samples: the limiter had counted "
                         f"{counted:.0f}, now {self.limiter.stats()['samples']:.0f}")
            return wire.SampleReply(False, "synced", self.store.num_inserted)
        wait = float(req.wait_s)
        wait = min(max(wait, 0.0), 10.0) if math.isfinite(wait) else 0.0  # NaN compares false: not min/max
        batch, reason = (local or self.local).draw(req.batch_size, wait)
        if batch is None:
            if reason != "rate limited":  # answered at once: keep a polling learner from spinning
                time.sleep(min(wait, 0.2))
            return wire.SampleReply(False, reason, self.store.num_inserted)
        self.samples_served += 1
        return self._reply(batch)

    def unscored(self, req: wire.UnscoredRequest) -> wire.SampleReply:
        """The oldest unscored rows from req.after on (collect-timing scoring); not rate limited."""
        if not 1 <= req.limit <= MAX_BATCH or req.after < 0:
            raise wire.WireError(f"unscored request after {req.after}, limit {req.limit}")
        n = self.store.num_inserted  # read first: anything newer is past the scan
        batch = self.store.get_unscored(req.after, req.limit)
        if batch is None:
            return wire.SampleReply(False, "none unscored", n)
        return encode_reply(batch, n)

    def _reply(self, batch: dict[str, np.ndarray]) -> wire.SampleReply:
        return encode_reply(batch, self.store.num_inserted)

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
            write_error=self.write_error or (
                f"snapshot: {self.store.snapshot_error}" if self.store.snapshot_error else ""),
        )

    def run(self) -> None:
        s, k = self.session, self.keys
        if not faults.claim_run_role(s, k, "replay", self.stop, self.log):
            return
        with (
            s.declare_subscriber(k.insert_all, self._on_insert),
            s.declare_subscriber(k.intrinsic, self._on_intrinsic),
            s.declare_subscriber(k.stop, self._on_stop),
            s.declare_queryable(k.sample, self._on_sample_query),
            s.declare_queryable(k.unscored, self._on_unscored_query),
            run_config.serve(s, k, self.run_config),
            s.liveliness().declare_token(k.alive("replay", 0)),  # last: once seen, all of the above answer
        ):
            self._threads = [threading.Thread(target=self._insert_loop, name="insert", daemon=True)]
            for i in range(max(1, self.args.sample_threads)):
                seed = self.config.seed * 1000 + self.store.num_inserted + i
                self._threads.append(threading.Thread(
                    target=self._serve_loop, args=(self._queries, self.sampler(seed)), name=f"sample{i}",
                    daemon=True,
                ))
            # Unscored rows on their own thread: training requests may wait on the rate limiter.
            self._threads.append(threading.Thread(
                target=self._serve_loop, args=(self._unscored, self.unscored), name="unscored", daemon=True
            ))
            for t in self._threads:
                t.start()
            n, budget = self.store.num_inserted, self.config.steps
            self.log(f"serving run {k.run_id}: {n} transitions, budget {budget}")
            while not self.stop.wait(self.args.stats_every_s):
                if dead := [t.name for t in self._threads if not t.is_alive()]:
                    # A live process that does nothing is never restarted: exit, non-zero.
                    raise faults.WorkerDied(f"replay worker thread(s) {', '.join(dead)} died")
                s.put(k.replay_stats, wire.encode(self.stats()))
                try:
                    self.store.sync_if_due()
                except OSError as err:  # the next write tries again, and stops inserts if it fails
                    self.log.every("sync", 60.0, f"cannot fsync the log: {err}")
                if self.store.snapshot_error:  # the log goes on; the next snapshot tries again
                    self.log.every("snapshot", 60.0, f"the last snapshot failed: {self.store.snapshot_error}")
                self.store.snapshot_if_due(self.args.snapshot_every)
            self.log(f"stopping ({self.stop.reason})")
            if self.limiter is not None:
                self.limiter.close()
            for t in self._threads:
                t.join(timeout=5.0)
            s.put(k.replay_stats, wire.encode(self.stats()))
        self.store.flush()
        self.store.close()


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: ReplayArgs, session: zenoh.Session, stop: StopFlag) -> None:
        # The run folder's config (written now if new; else compared: ConfigMismatch, exit 2).
        # A replay restarted with a new step budget continues its run.
        with faults.lock_service(Path(args.data), "replay"):  # before the folder is touched
            may_change = run_config.RESUME_MAY_CHANGE
            run = run_config.open_folder(args.config, Path(args.data), may_change=may_change)
            try:
                service = ReplayService(args, session, stop, run)
            except OpenStopped as err:  # run_service then exits 128 + the signal
                Log("replay")(f"stopped ({stop.reason}) before serving: {err}; nothing was lost, the next "
                              "start reads the whole log")
                return
            service.run()

    run_service(ReplayArgs, argv, "python -m services.replay", run, check_args)
