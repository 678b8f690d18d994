"""The actor service: steps one environment with a local policy copy and streams transitions.

- Acting: uniform random while the global env step count (from the replay's
  acknowledgements and stats) is below warmup_steps, then the local policy
  with exploration noise (config.agent.exploration_noise). Acting never waits
  for weights: the weights subscriber only parks the newest message, and the
  loop loads it between steps (latest wins).
- Streaming: each new frame is sent once, in batches of `batch` transitions
  (or fewer at an episode end), delta-coded and zstd-compressed, on a
  publisher with congestion control BLOCK. At most `max_in_flight` batches
  wait for the replay's acknowledgement: when the replay's rate limiter holds
  inserts back, the actor waits here (backpressure).
- Identity: `actor_id` (stable for a slot, e.g. the launcher's index) and a new
  incarnation at each start (tenths of a second since 2025, so it grows across
  restarts, as the replay requires). The env and exploration seeds derive from
  (config.seed, actor_id, incarnation). A liveliness token
  alive/actor/<id>/<incarnation> announces it; a status heartbeat every second.
- Replay loss: the actor watches the replay's liveliness token. While the
  replay is gone it does not act (its transitions would go nowhere); when the
  token disappears, the unacknowledged batches count as lost and the episode
  under way is abandoned, so the first batch after the replay's return starts
  a new episode, which the replay accepts (it never stitches across a gap).
"""

from __future__ import annotations

import os
import random
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch
import zenoh

from shared import envs, wire
from shared.agents import collect_action, make_agent
from shared.service import Log, StopFlag
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK


def new_incarnation() -> int:
    """Tenths of a second since 2025-01-01: grows across restarts (fits 31 bits until 2031)."""
    return wire.restart_stamp(10, 31)


def _default_actor_id() -> int:
    env = os.environ.get("NASA_ACTOR_ID")
    return int(env) if env else -1


@dataclass
class ActorArgs(ServiceArgs):
    """An actor: steps its environment with the latest policy and streams transitions to the replay."""

    actor_id: int = field(default_factory=_default_actor_id)
    """This actor's id (env NASA_ACTOR_ID); -1: a random one (replicas of a scaled service)."""
    actor_device: str = "cpu"
    """Device the local policy runs on."""
    send_batch: int = 8
    """Transitions per message."""
    max_in_flight: int = 4
    """Unacknowledged batches before the actor waits for the replay."""
    status_every_s: float = 1.0
    threads: int = 1
    """torch threads for acting."""


class StepRate:
    """Env steps per second over the last `window_s` seconds.

    Not over the last second: backpressure from the replay pauses an actor for
    seconds at a time, and a 1-s rate then reads 0 for an actor that is working.
    """

    def __init__(self, start: float, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self._points: deque[tuple[float, int]] = deque([(start, 0)])

    def update(self, now: float, steps: int) -> float:
        self._points.append((now, steps))
        while len(self._points) > 2 and now - self._points[1][0] >= self.window_s:
            self._points.popleft()  # keep the newest point that is at least window_s old
        t0, s0 = self._points[0]
        return (steps - s0) / (now - t0) if now > t0 else 0.0


class ActorService:
    def __init__(self, args: ActorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        c = args.config
        self.args, self.config, self.session, self.stop = args, c, session, stop
        self.keys = wire.Keys(args.run_id)
        self.actor_id = args.actor_id if args.actor_id >= 0 else random.SystemRandom().randrange(1000, 2**31)
        self.incarnation = new_incarnation()
        self.log = Log(f"actor {self.actor_id}")
        seeds = np.random.SeedSequence([c.seed, self.actor_id, self.incarnation]).generate_state(2)
        self.env = envs.from_config(c.env, int(seeds[0]) % 2**31)
        self.rng = np.random.default_rng(int(seeds[1]))
        torch.manual_seed(int(seeds[1]))
        torch.set_num_threads(max(1, args.threads))
        self.agent = make_agent(
            c.algo, self.env.obs_shape, self.env.action_dim, c.agent, torch.device(args.actor_device)
        )
        self.policy_version = 0
        self._held: tuple[int, int] | None = None  # (learner epoch, version) of the loaded weights
        self.env_steps = 0
        self.episodes = 0
        self.global_steps = 0  # newest replay count seen
        self.replay_done = False
        self.invalid = 0
        self._finished: list[list[float]] = []
        self._pending_weights: bytes | None = None
        self._cv = threading.Condition()
        self._in_flight = 0
        self._replay_alive = False
        self._episode_broken = False  # the replay went away during the episode under way
        self._seq = 0
        self._rate = StepRate(time.monotonic())
        self.steps_per_s = 0.0

    # -- callbacks ------------------------------------------------------------------------

    def _on_weights(self, sample: zenoh.Sample) -> None:
        self._pending_weights = sample.payload.to_bytes()  # latest wins; decoded by the loop

    def _on_weights_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None and self._pending_weights is None and self._held is None:
            self._pending_weights = reply.ok.payload.to_bytes()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = wire.decode(sample.payload.to_bytes(), wire.InsertAck)
        except wire.WireError as err:
            return self._invalid(f"ack: {err}")
        if ack.incarnation != self.incarnation:
            return
        with self._cv:
            self._in_flight = max(0, self._in_flight - 1)
            self.global_steps = max(self.global_steps, ack.num_inserted)
            self._cv.notify_all()

    def _on_replay_alive(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self._replay_alive = sample.kind == zenoh.SampleKind.PUT
            if not self._replay_alive:
                self._in_flight = 0  # never acknowledged: the replay did not store them, or lost the acks
                self._episode_broken = True
                self.log("the replay is gone: pausing, and abandoning the episode under way")
            self._cv.notify_all()

    def _await_replay(self) -> None:
        with self._cv:
            while not self._replay_alive and not self.stop:
                self.log.every("await", 10.0, f"waiting for the replay ({self.keys.alive('replay', 0)})")
                self._cv.wait(0.5)

    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            stats = wire.decode(sample.payload.to_bytes(), wire.ReplayStats)
        except wire.WireError as err:
            return self._invalid(f"replay stats: {err}")
        self.global_steps = max(self.global_steps, stats.num_inserted)
        self.replay_done = stats.done

    def _on_stop(self, sample: zenoh.Sample) -> None:
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except wire.WireError as err:
            self._invalid(f"stop: {err}")
        with self._cv:
            self._cv.notify_all()

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    # -- weights ----------------------------------------------------------------------------

    def maybe_load_weights(self) -> None:
        data, self._pending_weights = self._pending_weights, None
        if data is None:
            return
        try:
            msg = wire.decode(data, wire.Weights)
            if not wire.newer_weights(msg, self._held):
                return
            self.agent.load_policy_state_dict(wire.unpack_tensors(msg.tensors))
        except (wire.WireError, RuntimeError, KeyError) as err:  # torch raises RuntimeError on bad shapes
            return self._invalid(f"weights: {err}")
        self._held = (msg.epoch, msg.version)
        self.policy_version = msg.version
        self.global_steps = max(self.global_steps, msg.env_steps)

    # -- streaming --------------------------------------------------------------------------

    def _send(self, publisher: zenoh.Publisher, episode: int, start: int, first: np.ndarray | None,
              steps: list[tuple]) -> None:
        with self._cv:
            waited = time.monotonic()
            while self._in_flight >= self.args.max_in_flight and not self.stop:
                self._cv.wait(0.5)
                if time.monotonic() - waited > 60.0:  # the replay restarted and lost them
                    self.log("no acknowledgement for 60 s: assuming the in-flight batches lost")
                    self._in_flight = 0
            if self.stop:
                return
            self._in_flight += 1
        actions, rewards, discounts, frames, lasts, versions = zip(*steps, strict=True)
        msg = wire.TransitionBatch(
            actor_id=self.actor_id,
            incarnation=self.incarnation,
            episode=episode,
            start=start,
            seq=self._seq,
            n=len(steps),
            frame_shape=list(frames[0].shape),
            frames=wire.encode_frames(np.stack(frames)),
            first_frame=wire.encode_frames(first[None]) if first is not None else None,
            actions=np.asarray(actions, "<f4").tobytes(),
            rewards=np.asarray(rewards, "<f4").tobytes(),
            discounts=np.asarray(discounts, "<f4").tobytes(),
            lasts=np.asarray(lasts, "u1").tobytes(),
            policy_versions=np.asarray(versions, "<i8").tobytes(),
        )
        self._seq += 1
        publisher.put(wire.encode(msg))

    def _publish_status(self) -> None:
        self.steps_per_s = self._rate.update(time.monotonic(), self.env_steps)
        finished, self._finished = self._finished, []
        status = wire.ActorStatus(
            self.actor_id, self.incarnation, self.env_steps, self.episodes, self.policy_version,
            self.steps_per_s, finished,
        )
        self.session.put(self.keys.actor_status(self.actor_id), wire.encode(status))

    def _status_loop(self) -> None:
        while not self.stop.wait(self.args.status_every_s):
            self._publish_status()

    # -- the loop -----------------------------------------------------------------------------

    def run(self) -> None:
        s, k, c = self.session, self.keys, self.config
        with (
            s.declare_subscriber(k.weights, self._on_weights),
            s.declare_subscriber(k.ack(self.actor_id), self._on_ack),
            s.declare_subscriber(k.replay_stats, self._on_stats),
            s.declare_subscriber(k.stop, self._on_stop),
            s.liveliness().declare_subscriber(k.alive("replay", 0), self._on_replay_alive, history=True),
            s.declare_publisher(k.insert(self.actor_id), congestion_control=BLOCK) as publisher,
            s.liveliness().declare_token(k.alive("actor", self.actor_id, self.incarnation)),
        ):
            s.get(k.weights_latest, self._on_weights_reply, timeout=10.0)
            self.log(f"incarnation {self.incarnation} acting on {c.env.task} (run {k.run_id})")
            status = threading.Thread(target=self._status_loop, daemon=True)
            status.start()
            self._act_loop(publisher)
            self._publish_status()
            self.log(f"stopping after {self.env_steps} steps ({self.stop.reason})")
            status.join(timeout=2.0)

    def _act_loop(self, publisher: zenoh.Publisher) -> None:
        c, env, agent = self.config, self.env, self.agent
        episode = -1
        while not self.stop:
            if self.replay_done:  # the run's step budget is reached: wait for the stop
                self.stop.wait(0.2)
                continue
            self._await_replay()
            with self._cv:
                self._episode_broken = False
            ts = env.reset()
            episode += 1
            first: np.ndarray | None = ts.frame
            start, steps, total = 0, [], 0.0
            while not self.stop and not self.replay_done and not self._episode_broken:
                self.maybe_load_weights()
                warming_up = self.global_steps < c.warmup_steps
                action = collect_action(agent, ts.obs, warming_up, self.rng, env.action_dim)
                ts = env.step(action)
                self.env_steps += 1
                total += ts.reward
                steps.append((
                    action, ts.reward, envs.stored_discount(ts, c.env.time_limit), ts.frame, ts.last,
                    self.policy_version,
                ))
                if len(steps) >= self.args.send_batch or ts.last:
                    self._send(publisher, episode, start, first, steps)
                    start += len(steps)
                    first, steps = None, []
                if ts.last:
                    self.episodes += 1
                    self._finished.append([total, start])
                    break


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: ActorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        ActorService(args, session, stop).run()

    run_service(ActorArgs, argv, "python -m services.actor", run)
