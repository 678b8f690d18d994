"""The learner service: batches from the replay, intrinsic scores, updates, weights, status.

- Batches: `prefetch` threads each keep one sample request in flight to the
  replay's queryable and queue the decoded batch, so the compute thread finds
  the next batch ready. The replay's rate limiter paces the requests.
- Intrinsic rewards (nasa_td3, collect timing): each transition is scored
  once, soon after the replay stores it, with the learner's networks of that
  moment (the paper scores at collection with the single process's networks).
  The replay stores warm-up transitions with 0 (as the reference) and later
  ones unscored (NaN). Before each update the learner asks the replay for the
  oldest unscored transitions it has not seen (`SampleRequest.unscored_after`,
  served on its own replay thread, outside the rate limiter), scores them in
  one batched `agent.score` and writes the scores back (`replay/intrinsic`).
  A training batch that still brings an unscored row (the learner fell behind,
  or a write-back was lost to a replay restart) scores it then. A small cache
  covers rows that come back before their write-back lands.
- Weights: version = the update count; published every `publish_every`
  updates (DROP: latest wins, a lost message is replaced by the next) and
  served on `learner/weights/latest` for actors that just started.
- Evaluation results from the evaluator become eval.csv rows; episode
  returns reported by actors become train.csv rows (shared/runlog.py, the
  trainer's format).
- Checkpoint (atomic, shared/checkpoint.py) in <data>/learner/ every
  checkpoint_every global env steps, at the end and on SIGTERM/SIGINT; a
  restarted learner resumes from it (the replay keeps its own data).
- When it stops, the learner writes its last /status to <data>/learner/status.json,
  so a finished run's counts outlive the status API.
- The run ends when the replay's step budget is reached and the learner has
  done G * (steps - warmup) updates (or the limiter allows no more); the
  learner then waits for the last evaluation, checkpoints, and publishes Stop.
"""

from __future__ import annotations

import json
import math
import os
import queue
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import zenoh

from shared import checkpoint, envs, wire
from shared.agents import batch_to_device, make_agent
from shared.config import to_dict
from shared.device import resolve_device
from shared.runlog import TRAIN_FIELDS, CsvLog, eval_fields, read_rows
from shared.service import Log, StopFlag
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK
CHECKPOINT = "learner/checkpoint.pt"
FINAL_STATUS = "learner/status.json"


@dataclass
class LearnerArgs(ServiceArgs):
    """The learner: updates the agent from replay batches, publishes weights, serves /status."""

    data: Path = field(default_factory=lambda: Path(os.environ.get("NASA_DATA", "runs/default")))
    """Run folder: config.json, eval.csv, train.csv, learner/checkpoint.pt, learner/status.json
    (env NASA_DATA)."""
    host: str = field(default_factory=lambda: os.environ.get("NASA_STATUS_HOST", "127.0.0.1"))
    """Address of the status API (env NASA_STATUS_HOST; 0.0.0.0 in a container)."""
    port: int = field(default_factory=lambda: int(os.environ.get("NASA_STATUS_PORT", "8000")))
    """Port of the status API (env NASA_STATUS_PORT)."""
    publish_every: int = 20
    """K: publish weights every K updates."""
    prefetch: int = 2
    """Sample requests kept in flight."""
    final_eval_wait_s: float = 300.0
    """At the end, how long to wait for the evaluation of the last eval step."""
    threads: int = 0
    """torch threads (0: torch's default)."""


class Learner:
    def __init__(self, args: LearnerArgs, session: zenoh.Session, stop: StopFlag, action_dim: int) -> None:
        c = args.config
        self.args, self.config, self.session, self.stop = args, c, session, stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("learner")
        if args.threads > 0:
            torch.set_num_threads(args.threads)
        self.device = resolve_device(c.device)
        k, size = c.env.frame_stack, c.env.image_size
        self.obs_shape = (3 * k, size, size)
        self.action_dim = action_dim
        self.agent = make_agent(c.algo, self.obs_shape, action_dim, c.agent, self.device)
        self.rng = np.random.default_rng(c.seed)
        torch.manual_seed(c.seed)
        self.out = Path(args.data)
        self.out.mkdir(parents=True, exist_ok=True)
        config_path = self.out / "config.json"
        if not config_path.exists():
            config_path.write_text(json.dumps(to_dict(c), indent=2) + "\n")
        self.eval_log = CsvLog(self.out / "eval.csv", eval_fields(c.eval_episodes))
        self.train_log = CsvLog(self.out / "train.csv", TRAIN_FIELDS)
        self.scoring = self.agent.uses_intrinsic and c.agent.intrinsic_timing == "collect"
        self.target_updates = c.updates_per_step * max(0, c.steps - c.warmup_steps)

        self._lock = threading.Lock()
        self.env_steps = 0
        self.replay = {"size": 0, "bytes": 0, "done": False, "invalid": 0, "dropped": 0, "inserts": 0,
                       "samples": 0}
        self.policy_version = 0
        self.invalid = 0
        self.actors: dict[int, dict] = {}
        self.losses: dict[str, float] = {}
        # scored_at_first_sample: rows a training batch brought before score_new reached them.
        self.intrinsic = {
            "novelty_mean": None, "surprise_mean": None, "scored": 0, "scored_at_first_sample": 0,
        }
        self.eval = {"step": None, "mean": None, "std": None}
        self.episodes = 0
        self.wall_s = 0.0
        self.last_checkpoint_step = 0
        self.starved_when_done = False
        self._batches: queue.Queue[dict] = queue.Queue(maxsize=max(1, args.prefetch))
        self._evals: queue.Queue[wire.EvalResult] = queue.Queue()
        self._episode_rows: queue.Queue[tuple[int, float, float]] = queue.Queue()
        self._scored: OrderedDict[int, float] = OrderedDict()
        self._unscored_after = 0  # every row below this was scored or found scored
        self._rates: deque[tuple[float, int, int]] = deque(maxlen=64)
        self._weights_msg: bytes | None = None
        self._started = time.monotonic()
        self.epoch = wire.restart_stamp(1000, 62)  # orders weights across learner restarts
        self.resumed = False
        if (self.out / CHECKPOINT).exists():
            self.restore(checkpoint.load(self.out / CHECKPOINT, self.device))
        rows = read_rows(self.out / "eval.csv")
        if rows:
            last = rows[-1]
            self.eval = {"step": int(last["step"]), "mean": float(last["mean"]), "std": float(last["std"])}

    # -- checkpoint --------------------------------------------------------------------

    def save_checkpoint(self) -> None:
        checkpoint.save(
            self.out / CHECKPOINT,
            {
                "agent": self.agent.state_dict(),
                "rng": checkpoint.rng_state(self.rng),
                "env_steps": self.env_steps,
                "episodes": self.episodes,
                "wall_s": self.wall_s,
                "policy_version": self.policy_version,
                "updates": self.agent.num_updates,
            },
        )
        self.last_checkpoint_step = self.env_steps

    def write_final_status(self) -> None:
        """The last /status, in the run folder (atomically: a reader never sees half of it)."""
        path = self.out / FINAL_STATUS
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.status(), indent=2) + "\n")
        os.replace(tmp, path)

    def restore(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        checkpoint.restore_rng_state(self.rng, state["rng"])
        self.env_steps = self.last_checkpoint_step = int(state["env_steps"])
        self.episodes = int(state["episodes"])
        self.wall_s = float(state["wall_s"])
        self.policy_version = int(state["policy_version"])
        self.resumed = True
        self.log(f"resumed from checkpoint: {self.agent.num_updates} updates, env step {self.env_steps}")

    # -- Zenoh callbacks ----------------------------------------------------------------

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            s = wire.decode(sample.payload.to_bytes(), wire.ReplayStats)
        except wire.WireError as err:
            return self._invalid(f"replay stats: {err}")
        with self._lock:
            self.env_steps = max(self.env_steps, s.num_inserted)
            self.replay = {"size": s.size, "bytes": s.bytes, "done": s.done, "invalid": s.invalid,
                           "dropped": s.dropped, "inserts": s.inserts, "samples": s.samples}

    def _on_actor_status(self, sample: zenoh.Sample) -> None:
        try:
            s = wire.decode(sample.payload.to_bytes(), wire.ActorStatus)
        except wire.WireError as err:
            return self._invalid(f"actor status: {err}")
        with self._lock:
            a = self.actors.get(s.actor_id)
            if a is None or s.incarnation > a["incarnation"]:
                a = self.actors[s.actor_id] = self._new_actor(s.actor_id, s.incarnation, alive=True)
            if s.incarnation == a["incarnation"]:
                a.update(env_steps=s.env_steps, policy_version=s.policy_version,
                         steps_per_s=round(s.steps_per_s, 2), episodes=s.episodes, last_seen=time.monotonic())
        for entry in s.episode_returns:
            if isinstance(entry, list) and len(entry) == 2:
                self._episode_rows.put((s.actor_id, float(entry[0]), float(entry[1])))

    @staticmethod
    def _new_actor(actor_id: int, incarnation: int, alive: bool) -> dict:
        return {"id": actor_id, "incarnation": incarnation, "alive": alive, "env_steps": 0,
                "episodes": 0, "last_seen": time.monotonic(), "policy_version": 0, "steps_per_s": 0.0}

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            role, ident, inc = self.keys.parse_alive(str(sample.key_expr))
            if role != "actor" or inc is None:
                return
            actor_id = int(ident)
        except (wire.WireError, ValueError) as err:
            return self._invalid(f"liveliness key: {err}")
        put = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            a = self.actors.get(actor_id)
            if put and (a is None or inc > a["incarnation"]):
                self.actors[actor_id] = self._new_actor(actor_id, inc, alive=True)
            elif a is not None and inc == a["incarnation"]:
                a["alive"] = put
                a["last_seen"] = time.monotonic()

    def _on_eval(self, sample: zenoh.Sample) -> None:
        try:
            self._evals.put(wire.decode(sample.payload.to_bytes(), wire.EvalResult))
        except wire.WireError as err:
            self._invalid(f"eval result: {err}")

    def _on_stop(self, sample: zenoh.Sample) -> None:
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except wire.WireError as err:
            self._invalid(f"stop: {err}")

    def _on_weights_query(self, query: zenoh.Query) -> None:
        if self._weights_msg is not None:
            query.reply(self.keys.weights_latest, self._weights_msg)
        query.drop()

    # -- batches ------------------------------------------------------------------------

    def _prefetch_loop(self) -> None:
        request = wire.encode(wire.SampleRequest(self.config.batch_size, wait_s=1.0))
        while not self.stop:
            try:
                replies = self.session.get(
                    self.keys.sample, payload=request, timeout=30.0, congestion_control=BLOCK
                )
                batch, answered = None, False
                for reply in replies:
                    if reply.ok is None:
                        continue
                    answered = True
                    batch = self._decode_batch(reply.ok.payload.to_bytes())
            except wire.WireError as err:
                self._invalid(f"sample reply: {err}")
                continue
            except zenoh.ZError as err:
                if self.stop:
                    return
                self.log.every("get", 5.0, f"sample request failed: {err}")
                self.stop.wait(0.5)
                continue
            if batch is None:  # not ready yet (warm-up, rate limit) or no replay: ask again
                if self.replay["done"]:
                    self.starved_when_done = True
                if not answered:  # no replay yet: do not spin
                    self.stop.wait(0.2)
                continue
            while not self.stop:
                try:
                    self._batches.put(batch, timeout=0.2)
                    break
                except queue.Full:
                    continue

    def _decode_batch(self, data: bytes) -> dict | None:
        r = wire.decode(data, wire.SampleReply)
        with self._lock:
            self.env_steps = max(self.env_steps, r.num_inserted)
        return self._batch_from_reply(r) if r.ok else None

    def _batch_from_reply(self, r: wire.SampleReply) -> dict:
        b, k = r.batch_size, self.config.env.frame_stack
        shape = tuple(r.window_shape)
        expected = (b, 3 * (k + 1), *self.obs_shape[1:])
        if shape != expected:
            raise wire.WireError(f"window shape {shape}, expected {expected}")
        window = wire.array(r.window, "u1", shape).copy()  # one writable copy; obs, next_obs view it
        a = self.action_dim
        return {
            "obs": window[:, : 3 * k],
            "next_obs": window[:, 3:],
            "action": wire.array(r.action, "<f4", (b, a)).copy(),
            "reward": wire.array(r.reward, "<f4", (b,)).copy(),
            "intrinsic": wire.array(r.intrinsic, "<f4", (b,)).copy(),
            "discount": wire.array(r.discount, "<f4", (b,)).copy(),
            "index": wire.array(r.index, "<i8", (b,)).copy(),
        }

    def score_new(self) -> None:
        """Collect timing: score transitions soon after the replay stores them, oldest first,
        at most one batch per update. Rows it has not reached yet are scored when a training
        batch first brings them (score_unscored)."""
        if self.env_steps <= self._unscored_after:
            return
        request = wire.SampleRequest(self.config.batch_size, wait_s=0.0, unscored_after=self._unscored_after)
        try:
            replies = self.session.get(
                self.keys.sample, payload=wire.encode(request), timeout=10.0, congestion_control=BLOCK
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                r = wire.decode(reply.ok.payload.to_bytes(), wire.SampleReply)
                if not r.ok:  # nothing unscored below r.num_inserted
                    self._unscored_after = max(self._unscored_after, r.num_inserted)
                    continue
                batch = self._batch_from_reply(r)
                self.score_unscored(batch, on_arrival=True)
                self._unscored_after = max(self._unscored_after, int(batch["index"].max()) + 1)
        except wire.WireError as err:
            self._invalid(f"unscored reply: {err}")
        except zenoh.ZError as err:
            self.log.every("unscored", 5.0, f"unscored request failed: {err}")

    def score_unscored(self, batch: dict[str, np.ndarray], on_arrival: bool = False) -> None:
        """Score rows never scored (NaN) once, use the scores, and write them back to the replay.

        A row scored before that comes back unscored had its write-back still in
        flight, or lost to a replay restart: it keeps its first score, sent again.
        A row drawn twice into one batch is scored once. `on_arrival`: the rows
        come from score_new (else a training batch brought them first).
        """
        rows = np.flatnonzero(np.isnan(batch["intrinsic"]))
        if len(rows) == 0:
            return
        index = batch["index"]
        fresh, again = [], []
        for r in rows.tolist():
            cached = self._scored.get(int(index[r]))
            if cached is not None:
                batch["intrinsic"][r] = cached
                again.append(r)
            else:
                fresh.append(r)
        if not fresh:
            self._write_back(index[again], batch["intrinsic"][again])
            return
        d = self.device
        fresh_rows = np.array(fresh)
        _, first, inverse = np.unique(index[fresh_rows], return_index=True, return_inverse=True)
        sel = fresh_rows[first]  # one row per distinct transition
        scores = self.agent.score(
            torch.as_tensor(batch["obs"][sel], device=d),
            torch.as_tensor(batch["action"][sel], device=d),
            torch.as_tensor(batch["next_obs"][sel], device=d),
        )
        values = scores["intrinsic"].float().cpu().numpy()
        batch["intrinsic"][fresh_rows] = values[inverse]
        for i, v in zip(index[sel].tolist(), values.tolist(), strict=True):
            self._scored[i] = v
        while len(self._scored) > 100_000:
            self._scored.popitem(last=False)
        both = np.concatenate([sel, np.array(again, dtype=sel.dtype)])
        self._write_back(index[both], batch["intrinsic"][both])
        n = self.intrinsic["scored"] + len(sel)
        if not on_arrival:
            self.intrinsic["scored_at_first_sample"] += len(sel)
        means = {name: scores[name].mean().item() for name in ("novelty", "surprise")}
        for name, mean in means.items():
            old = self.intrinsic[f"{name}_mean"]
            self.intrinsic[f"{name}_mean"] = mean if old is None else old + (mean - old) * len(sel) / n
        self.intrinsic["scored"] = n
        self._train_intrinsic.append((means["novelty"], means["surprise"]))

    def _write_back(self, index: np.ndarray, values: np.ndarray) -> None:
        msg = wire.SetIntrinsic(index.astype("<i8").tobytes(), values.astype("<f4").tobytes())
        self.session.put(self.keys.intrinsic, wire.encode(msg), congestion_control=BLOCK)

    # -- the loop -------------------------------------------------------------------------

    def publish_weights(self, publisher: zenoh.Publisher) -> None:
        self.policy_version = self.agent.num_updates
        tensors = wire.pack_tensors(self.agent.policy_state_dict())
        msg = wire.Weights(self.epoch, self.policy_version, self.env_steps, tensors)
        self._weights_msg = wire.encode(msg)
        publisher.put(self._weights_msg)

    def run(self) -> None:
        from services.learner.status_api import StatusServer, make_app

        s, k = self.session, self.keys
        server = StatusServer(make_app(self.status, self.healthy), self.args.host, self.args.port)
        server.start()
        try:
            with (
                s.declare_subscriber(k.replay_stats, self._on_stats),
                s.declare_subscriber(k.actor_status_all, self._on_actor_status),
                s.declare_subscriber(k.eval_result, self._on_eval),
                s.declare_subscriber(k.stop, self._on_stop),
                s.liveliness().declare_subscriber(k.alive_actors, self._on_alive, history=True),
                s.declare_queryable(k.weights_latest, self._on_weights_query),
                s.declare_publisher(k.weights) as publisher,
                s.liveliness().declare_token(k.alive("learner", 0)),
            ):
                self.log(f"run {k.run_id}: status on http://{self.args.host}:{self.args.port}/status")
                self._loop(publisher)
        finally:
            server.stop()

    def _loop(self, publisher: zenoh.Publisher) -> None:
        agent = self.agent
        self.publish_weights(publisher)
        threads = [threading.Thread(target=self._prefetch_loop, name=f"prefetch{i}", daemon=True)
                   for i in range(max(1, self.args.prefetch))]
        for t in threads:
            t.start()
        self._metric_sums: dict[str, list[float]] = {}
        self._train_intrinsic: list[tuple[float, float]] = []
        wall_start, wall0 = time.monotonic(), self.wall_s
        finished = False
        while not self.stop:
            self.wall_s = wall0 + time.monotonic() - wall_start
            self._drain_side_queues()
            self._maybe_checkpoint()
            if self.replay["done"] and (agent.num_updates >= self.target_updates or self.starved_when_done):
                finished = True
                break
            try:
                batch = self._batches.get(timeout=0.2)
            except queue.Empty:
                continue
            if self.scoring:
                self.score_new()
                self.score_unscored(batch)
            metrics = agent.update(batch_to_device(batch, self.device))
            self._record(metrics)
            if agent.num_updates % self.args.publish_every == 0:
                self.publish_weights(publisher)
        if finished:
            if self.scoring:
                while self._unscored_after < self.env_steps and not self.stop:  # the last arrivals
                    before = self._unscored_after
                    self.score_new()
                    if self._unscored_after == before:
                        break
            self.publish_weights(publisher)
            self._wait_final_eval()
        self.save_checkpoint()
        self.write_final_status()
        if finished:
            self.log(f"run done: {self.env_steps} env steps, {agent.num_updates} updates")
            self.session.put(self.keys.stop, wire.encode(wire.Stop("run done")), congestion_control=BLOCK)
        else:
            self.log(f"stopping ({self.stop.reason}); checkpoint at {agent.num_updates} updates")
        self.stop.set("done")
        for t in threads:
            t.join(timeout=5.0)

    def _wait_final_eval(self) -> None:
        c = self.config
        last = (min(self.env_steps, c.steps) // c.eval_every) * c.eval_every
        deadline = time.monotonic() + self.args.final_eval_wait_s
        while not self.stop and time.monotonic() < deadline:
            self._drain_side_queues()
            if self.eval["step"] is not None and self.eval["step"] >= last:
                return
            time.sleep(0.1)

    def _record(self, metrics: dict[str, float]) -> None:
        for key, value in metrics.items():
            self._metric_sums.setdefault(key, []).append(value)
            old = self.losses.get(key)
            self.losses[key] = value if old is None else 0.95 * old + 0.05 * value

    def _sample_rates(self) -> None:
        """Keep (time, env steps, updates) every 0.5 s for the rates /status reports."""
        now = time.monotonic()
        if not self._rates or now - self._rates[-1][0] >= 0.5:
            self._rates.append((now, self.env_steps, self.agent.num_updates))

    def _maybe_checkpoint(self) -> None:
        c = self.config
        if self.env_steps // c.checkpoint_every > self.last_checkpoint_step // c.checkpoint_every:
            self.save_checkpoint()

    def _drain_side_queues(self) -> None:
        self._sample_rates()
        while True:
            try:
                r = self._evals.get_nowait()
            except queue.Empty:
                break
            if self.eval["step"] is not None and r.step <= self.eval["step"]:
                continue  # an evaluation already recorded (e.g. sent again after a restart)
            returns = [float(x) for x in r.returns][: self.config.eval_episodes]
            row = {"step": r.step, "mean": float(np.mean(returns)), "std": float(np.std(returns))}
            row |= {f"return_{i}": v for i, v in enumerate(returns)}
            self.eval_log.append(row)
            self.eval = {"step": r.step, "mean": row["mean"], "std": row["std"]}
            self.log(f"eval step {r.step} (policy {r.policy_version}): mean return {row['mean']:.1f}")
        while True:
            try:
                _, ret, length = self._episode_rows.get_nowait()
            except queue.Empty:
                break
            self.episodes += 1
            means = {k: float(np.mean(v)) for k, v in self._metric_sums.items() if k in TRAIN_FIELDS}
            if self._train_intrinsic:
                nov, sur = zip(*self._train_intrinsic, strict=True)
                means |= {"novelty_mean": float(np.mean(nov)), "surprise_mean": float(np.mean(sur))}
            self._metric_sums, self._train_intrinsic = {}, []
            self.train_log.append({
                "step": self.env_steps, "episode": self.episodes, "return": ret, "length": int(length),
                "updates": self.agent.num_updates, "wall_s": self.wall_s, **means,
            })

    # -- status ---------------------------------------------------------------------------

    def healthy(self) -> bool:
        return not self.stop

    def status(self) -> dict:
        c = self.config
        with self._lock:
            now = time.monotonic()
            actors = [
                {**{k: v for k, v in a.items() if k != "last_seen"},
                 "last_seen_s": round(now - a["last_seen"], 3)}
                for a in sorted(self.actors.values(), key=lambda a: a["id"])
            ]
            env_steps, replay = self.env_steps, dict(self.replay)
        updates = self.agent.num_updates
        rates = list(self._rates)
        env_rate = upd_rate = 0.0
        if len(rates) >= 2:
            recent = [r for r in rates if r[0] >= rates[-1][0] - 10.0]
            (t0, e0, u0), (t1, e1, u1) = recent[0], rates[-1]
            if t1 > t0:
                env_rate, upd_rate = (e1 - e0) / (t1 - t0), (u1 - u0) / (t1 - t0)
        learning_steps = env_steps - c.warmup_steps
        return {
            "run_id": self.keys.run_id,
            "algo": c.algo,
            "task": c.env.task,
            "device": str(self.device),
            "env_steps": env_steps,
            "steps_budget": c.steps,
            "warmup_steps": c.warmup_steps,
            "updates": updates,
            "updates_target_per_env_step": c.updates_per_step,
            "updates_per_env_step": updates / learning_steps if learning_steps > 0 else 0.0,
            "env_steps_per_s": round(env_rate, 3),
            "updates_per_s": round(upd_rate, 3),
            "replay": {"size": replay["size"], "bytes": replay["bytes"], "done": replay["done"],
                       "dropped": replay["dropped"], "invalid_messages": replay["invalid"],
                       "limiter_inserts": replay["inserts"], "limiter_samples": replay["samples"]},
            "policy_version": self.policy_version,
            "actors": actors,
            "eval": dict(self.eval),
            "intrinsic": {k: v for k, v in self.intrinsic.items()},
            "losses": {k: round(v, 6) for k, v in self.losses.items() if math.isfinite(v)},
            "invalid_messages": self.invalid,
            "resumed": self.resumed,
            "wall_s": round(self.wall_s, 3),
        }


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: LearnerArgs, session: zenoh.Session, stop: StopFlag) -> None:
        Learner(args, session, stop, envs.from_config(args.config.env, 0).action_dim).run()

    run_service(LearnerArgs, argv, "python -m services.learner", run)
