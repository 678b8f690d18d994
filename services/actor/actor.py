"""The actor service: steps one environment with a local policy copy and streams transitions.

- Acting: uniform random while the global env step count (from the replay's
  acknowledgements and stats) is below warmup_steps, then the local policy
  with exploration noise. Acting never waits for weights: the weights
  subscriber parks the newest message and the loop loads it between steps.
- Streaming: the environment loop hands each transition to the replay
  client's writer (`ZenohWriter`): batches, compressed frames, at most
  `max_in_flight` unacknowledged batches (backpressure from the replay's rate
  limiter), and the replay's liveliness.
- Identity: `actor_id` (stable for a slot) and a new incarnation at each start
  (tenths of a second since 2025, so it grows across restarts). The env and
  exploration seeds derive from (config.seed, actor_id, incarnation). A
  liveliness token alive/actor/<id>/<incarnation> announces it; a status
  heartbeat every second carries the episodes finished since the last.
- Replay loss: while the replay is gone the actor does not act; the episode
  under way is abandoned (the writer marks it broken), so the first batch
  after the replay's return starts a new episode.
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

from shared import envs, run_config, wire
from shared.agents import collect_action, make_agent
from shared.env_loop import EnvLoop
from shared.replay.adder import ZenohWriter
from shared.service import Log, StopFlag
from shared.weights import WeightsSubscriber
from shared.zenoh_session import ServiceArgs


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
    def __init__(self, args: ActorArgs, session: zenoh.Session, stop: StopFlag,
                 run: run_config.RunConfig) -> None:
        c = self.config = run.config
        self.args, self.session, self.stop = args, session, stop
        self.keys = wire.Keys(args.run_id)
        self.actor_id = args.actor_id if args.actor_id >= 0 else random.SystemRandom().randrange(1000, 2**31)
        self.incarnation = new_incarnation()
        self.log = Log(f"actor {self.actor_id}")
        seeds = np.random.SeedSequence([c.seed, self.actor_id, self.incarnation]).generate_state(2)
        self.env = envs.from_config(c.env, int(seeds[0]) % 2**31)
        self.rng = np.random.default_rng(int(seeds[1]))
        torch.manual_seed(int(seeds[1]))
        torch.set_num_threads(max(1, args.threads))
        spec = run.spec
        device = torch.device(args.actor_device)
        self.agent = make_agent(c.algo, spec.obs_shape, spec.action_dim, c.agent, device)
        self.weights = WeightsSubscriber(self.agent, self._invalid)
        self.writer = ZenohWriter(session, self.keys, self.actor_id, self.incarnation, spec.frame_shape,
                                  args.send_batch, args.max_in_flight, stop, self.log)
        self.invalid = 0
        self.episodes = 0
        self._finished: list[list[float]] = []
        self._rate = StepRate(time.monotonic())

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def _on_stop(self, sample: zenoh.Sample) -> None:
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except wire.WireError as err:
            self._invalid(f"stop: {err}")

    @property
    def policy_version(self) -> int:
        return self.weights.version or 0

    def _publish_status(self, env_steps: int) -> None:
        steps_per_s = self._rate.update(time.monotonic(), env_steps)
        finished, self._finished = self._finished, []
        status = wire.ActorStatus(self.actor_id, self.incarnation, env_steps, self.episodes,
                                  self.policy_version, steps_per_s, finished)
        self.session.put(self.keys.actor_status(self.actor_id), wire.encode(status))

    def run(self) -> None:
        s, k = self.session, self.keys
        loop = EnvLoop(self.env, self.writer, self.config.env.time_limit)
        with (
            self.writer,
            self.weights.subscribe(s, k),
            s.declare_subscriber(k.stop, self._on_stop),
            s.liveliness().declare_token(k.alive("actor", self.actor_id, self.incarnation)),
        ):
            self.log(f"incarnation {self.incarnation} acting on {self.config.env.task} (run {k.run_id})")
            status = threading.Thread(target=self._status_loop, args=(loop,), daemon=True)
            status.start()
            self._act(loop)
            self._publish_status(loop.steps)
            self.log(f"stopping after {loop.steps} steps ({self.stop.reason})")
            status.join(timeout=2.0)

    def _status_loop(self, loop: EnvLoop) -> None:
        while not self.stop.wait(self.args.status_every_s):
            self._publish_status(loop.steps)

    def _act(self, loop: EnvLoop) -> None:
        c, w = self.config, self.writer
        while not self.stop:
            if w.replay_done:  # the run's step budget is reached: wait for the stop
                self.stop.wait(0.2)
                continue
            w.wait_for_replay()
            if self.stop:
                return
            ts = loop.reset()
            while not self.stop and not w.replay_done and not w.broken:
                self.weights.maybe_load()
                warming_up = max(w.global_steps, self.weights.env_steps) < c.warmup_steps
                action = collect_action(self.agent, ts.obs, warming_up, self.rng, loop.env.spec.action_dim)
                ts = loop.step(action, self.policy_version)
                if ts.last:
                    self.episodes += 1
                    self._finished.append([loop.episode_return, loop.episode_length])
                    break


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: ActorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        run = run_config.join(args.config, session, wire.Keys(args.run_id), stop)
        ActorService(args, session, stop, run).run()

    run_service(ActorArgs, argv, "python -m services.actor", run)
