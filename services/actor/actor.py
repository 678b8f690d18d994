"""The actor service: steps one environment with a local policy copy and streams transitions.

- Acting: uniform random while the global env step count (from the replay's
  acknowledgements and stats, plus this actor's steps not acknowledged yet) is
  below warmup_steps, then the local policy with exploration noise. Acting
  waits for weights once, before its first policy step, until it holds the
  learner's; never after: the weights subscriber parks the newest message
  and the loop loads it between steps.
- Streaming: the environment loop hands each transition to the replay
  client's writer (`ZenohWriter`): batches, compressed frames, at most
  `max_in_flight` unacknowledged batches (backpressure from the replay's rate
  limiter), and the replay's liveliness.
- Identity: `actor_id` (stable for a slot) and a new incarnation at each start
  (tenths of a second since 2025, so it grows across restarts; past the last
  one made for the id on this host, so two launches in one tenth differ) and a
  random `launch` number, which its batches carry: launches on two hosts in
  one tenth share the incarnation, and the replay keeps the first it hears
  and refuses the other for good (it stops, below). The env and
  exploration seeds derive from (config.seed, actor_id, incarnation). A
  liveliness token alive/actor/<id>/<incarnation> announces it; a status
  heartbeat every second carries the episodes finished since the last.
- One process per actor id: an actor watches its id's tokens, and when a newer
  incarnation of its id appears (the same id started a second time, or a
  replacement started while this one was cut off) it stops with exit code 2,
  so no supervisor restarts it. The replay takes only the newest incarnation's
  episodes, so the older one would otherwise wait on acknowledgements for ever.
- Refusals: the replay acknowledges a batch it does not store with the reason;
  the heartbeat counts them, and when the replay says it will refuse every batch
  of this incarnation (it has taken a newer incarnation of this id, the id does
  not fit its store, frames of another shape) the actor stops with exit code 2
  and the reason.
- Replay loss: while the replay is gone the actor does not act; the episode
  under way is abandoned (the writer marks it broken), so the first batch
  after the replay's return starts a new episode.
- Robot bridge (`--bridge ID`): the environment is a bridge's (the gripper, or
  its stand-in, in its own process), stacked here. While the bridge's
  liveliness token is gone, or it refuses (e-stop, a fault, another client
  holding its gripper), the actor sends nothing and waits; the episode under
  way is abandoned and a new one starts when the bridge is back (or free).
- Reports: each heartbeat carries the environment's fault state where it has
  one (the bridge's safety state; the worst seen since the previous heartbeat)
  and the counts of a histogram of env step times.
"""

from __future__ import annotations

import bisect
import contextlib
import fcntl
import math
import os
import random
import secrets
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import zenoh

from services.robot_bridge.client import BRIDGE_LOST, BridgeHeld, BridgePresence, client_name
from shared import envs, run_config, wire
from shared.agents import collect_action, make_agent
from shared.config import ConfigError
from shared.env_loop import EnvLoop
from shared.replay.adder import SEND_BATCH, ZenohWriter
from shared.replay.store import ID_LIMIT
from shared.service import Log, MessageGuard, StopFlag
from shared.weights import WeightsSubscriber
from shared.zenoh_session import ServiceArgs, env_int

INCARNATIONS = Path(tempfile.gettempdir()) / "nasa-incarnations"
"""One file per actor id holding the last incarnation made for it on this host."""


def new_incarnation(actor_id: int, folder: Path = INCARNATIONS) -> int:
    """Tenths of a second since 2025-01-01: grows across restarts (fits 31 bits until 2031), and
    past the last one made for this id on this host (`folder`, under a lock). Two launches of an id
    in the same tenth got the same one: neither stopped, and the replay took the two streams for one.
    The later of the two is the newer, so the older stops as when superseded. Not random low bits:
    31 bits hold the time alone, and a store keeps the newest incarnation it saw of each id, which
    a new one must pass. Another host's launch in the same tenth is not seen here (the time alone):
    the actor's random launch number tells the two apart at the replay."""
    stamp = wire.restart_stamp(10, 31)
    try:
        folder.mkdir(exist_ok=True)
        fd = os.open(folder / str(actor_id), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:  # no folder to share (read-only, another user's): the time alone
        return stamp
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # released when fd closes
        text = os.read(fd, 32).decode(errors="replace").strip()
        last = int(text) if text.isdigit() else -1
        incarnation = last + 1 if stamp <= last < ID_LIMIT - 1 else stamp
        os.pwrite(fd, f"{incarnation:<12d}".encode(), 0)  # fixed width: no stale digits after it
        return incarnation
    except OSError:
        return stamp
    finally:
        os.close(fd)


MAX_ACTOR_ID = ID_LIMIT
"""Actor ids are below this: the replay refuses every episode of a larger one, which would leave
its actor acting for nothing."""


def _default_actor_id() -> int:
    return env_int("NASA_ACTOR_ID", -1)


@dataclass
class ActorArgs(ServiceArgs):
    """An actor: steps its environment with the latest policy and streams transitions to the replay."""

    actor_id: int = field(default_factory=_default_actor_id)
    """This actor's id, 0 to 2**31 - 1 (env NASA_ACTOR_ID); -1: a random one (replicas of a scaled
    service)."""
    actor_device: str = "cpu"
    """Device the local policy runs on."""
    send_batch: int = SEND_BATCH
    """Transitions per message."""
    max_in_flight: int = 4
    """Unacknowledged batches before the actor waits for the replay."""
    status_every_s: float = 1.0
    threads: int = 1
    """torch threads for acting."""
    bridge: str = ""
    """Step the environment through the robot bridge of this id (`python -m services.robot_bridge
    --bridge-id ID`) instead of in this process; "": in this process."""
    act_before_weights: bool = False
    """Benchmarks only: past the warm-up, act with this actor's own initial networks until the
    learner's weights come instead of waiting for them (an actor measured without a learner)."""


PAUSE_S = 1.0
"""How long an actor waits before it asks a bridge that refused (e-stop, fault) for a new episode."""
UNREADABLE_FAULT = "unreadable"
"""The fault state reported for an environment whose own cannot be read."""
WEIGHTS_POLL_S = 0.05
"""How often an actor past the warm-up looks for the learner's first weights."""


class StepTimes:
    """Env step times counted in the buckets of wire.STEP_SECONDS_BUCKETS since this incarnation
    began: a Prometheus histogram's figures, which each heartbeat carries to the learner."""

    def __init__(self) -> None:
        self.counts = [0] * (len(wire.STEP_SECONDS_BUCKETS) + 1)
        self.total_s = 0.0

    def observe(self, seconds: float) -> None:
        self.counts[bisect.bisect_left(wire.STEP_SECONDS_BUCKETS, seconds)] += 1
        self.total_s += seconds


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


class ActorService(MessageGuard):
    def __init__(self, args: ActorArgs, session: zenoh.Session, stop: StopFlag,
                 run: run_config.RunConfig) -> None:
        c = self.config = run.config
        self.args, self.session, self.stop = args, session, stop
        self.keys = wire.Keys(args.run_id)
        self.actor_id = (args.actor_id if args.actor_id >= 0
                         else random.SystemRandom().randrange(1000, MAX_ACTOR_ID))
        self.incarnation = new_incarnation(self.actor_id)
        # Random: another host's launch of this id in the same tenth gets the same incarnation.
        self.launch = secrets.randbelow(wire.MAX_INT - 1) + 1
        self.log = Log(f"actor {self.actor_id}")
        seeds = np.random.SeedSequence([c.seed, self.actor_id, self.incarnation]).generate_state(2)
        self.bridge: BridgePresence | None = None
        if args.bridge:
            envs.check_remote(c.env)
            self.bridge = BridgePresence(session, args.bridge)
        # A bridge's environment is built once the bridge is there (`_connect`).
        env_seed = int(seeds[0]) % 2**31
        self.env: envs.PixelEnv | None = None if args.bridge else envs.from_config(c.env, env_seed)
        self.loop: EnvLoop | None = None
        self.step_times = StepTimes()
        self._fault_seen: str | None = None
        self.rng = np.random.default_rng(int(seeds[1]))
        torch.manual_seed(int(seeds[1]))
        torch.set_num_threads(max(1, args.threads))
        spec = run.spec
        device = torch.device(args.actor_device)
        self.agent = make_agent(c.algo, spec.obs_shape, spec.action_dim, c.agent, device,
                                updates=False)
        self.weights = WeightsSubscriber(self.agent, self._invalid, steps=c.steps)
        self.writer = ZenohWriter(session, self.keys, self.actor_id, self.incarnation, spec.frame_shape,
                                  args.send_batch, args.max_in_flight, stop, self.log,
                                  budget=self.config.steps, launch=self.launch)
        self.episodes = 0
        self.env_faults = 0  # episodes lost to a diverged simulation or a non-finite action
        # Never replaced, only drained: the status thread's swap of a list could drop an episode
        # the main loop appended to the old one between reading it and appending.
        self._finished: deque[list[float]] = deque()
        self._rate = StepRate(time.monotonic())
        self.superseded_by: int | None = None
        self._older_seen: set[int] = set()
        self._held_by: str | None = None  # the other client holding the bridge's gripper, once said

    @property
    def policy_version(self) -> int:
        return self.weights.version or 0

    @property
    def env_steps(self) -> int:
        return self.loop.steps if self.loop is not None else 0

    def fault(self) -> str | None:
        """The environment's fault state now: a bridge that is gone is `bridge_lost`. A state that
        cannot be read (a bridge reply of another layout) is `unreadable`, and one longer than a
        state name is cut: the first ended the actor, the second had the learner refuse every
        heartbeat carrying it, and the episodes each reported."""
        if self.bridge is not None and (self.env is None or not self.bridge.present):
            return BRIDGE_LOST
        fault = getattr(self.env, "fault", None)
        if fault is None:
            return None
        try:
            state = fault()
        except (AttributeError, TypeError, ValueError, KeyError) as err:
            self.log.every("fault-state", 60.0, f"the environment's fault state cannot be read: "
                                                f"{type(err).__name__}: {err}")
            return UNREADABLE_FAULT
        return None if state is None else str(state)[:wire.MAX_FAULT_TEXT]

    def _note_fault(self) -> None:
        """Keep a fault met between two heartbeats for the next one, however briefly it lasted."""
        fault = self.fault()
        if fault not in (None, "ok"):
            self._fault_seen = fault

    def _publish_status(self) -> None:
        env_steps = self.env_steps
        steps_per_s = self._rate.update(time.monotonic(), env_steps)
        finished = [self._finished.popleft() for _ in range(len(self._finished))]
        fault, self._fault_seen = self._fault_seen or self.fault(), None
        times = self.step_times
        status = wire.ActorStatus(self.actor_id, self.incarnation, env_steps, self.episodes,
                                  self.policy_version, steps_per_s, finished, fault, list(times.counts),
                                  times.total_s, self.writer.refused)
        self.session.put(self.keys.actor_status(self.actor_id), wire.encode(status))

    def run(self) -> None:
        s, k = self.session, self.keys
        with (
            self.writer,
            self.weights.subscribe(s, k.weights, k.weights_latest),
            s.declare_subscriber(k.stop, self._on_stop),
            s.liveliness().declare_token(k.alive("actor", self.actor_id, self.incarnation)),
            s.liveliness().declare_subscriber(k.alive("actor", self.actor_id) + "/*", self._on_same_id,
                                              history=True),
            self.bridge if self.bridge is not None else contextlib.nullcontext(),
        ):
            where = f" through bridge {self.args.bridge}" if self.bridge is not None else ""
            task = self.config.env.task
            self.log(f"incarnation {self.incarnation} acting on {task}{where} (run {k.run_id})")
            status = threading.Thread(target=self._status_loop, daemon=True)
            status.start()
            if self._connect():
                self._act()
            self._publish_status()
            self.log(f"stopping after {self.env_steps} steps ({self.stop.reason})")
            status.join(timeout=2.0)
        if self.superseded_by is not None:
            raise ConfigError(
                f"actor id {self.actor_id} was started again (incarnation {self.superseded_by}); this "
                f"incarnation ({self.incarnation}) stops: give each actor its own --actor-id")
        if self.writer.refused_for_good is not None:
            raise ConfigError(
                f"the replay refuses every batch of actor id {self.actor_id} incarnation "
                f"{self.incarnation} ({self.writer.refused} refused): {self.writer.refused_for_good}")

    def _on_same_id(self, sample: zenoh.Sample) -> None:
        """Another process's token for this actor id: the newer incarnation keeps the id."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            _, _, other = self.keys.parse_alive(str(sample.key_expr))
        except (wire.WireError, ValueError) as err:
            return self._invalid(f"actor token: {err}")
        if other is None or other == self.incarnation:
            return
        if other > self.incarnation:
            self.superseded_by = other
            self.stop.set(f"a newer incarnation ({other}) of actor id {self.actor_id} started")
        elif other not in self._older_seen:
            self._older_seen.add(other)
            self.log(f"incarnation {other} of this actor id is still running: it stops, this one goes on")

    def _status_loop(self) -> None:
        while not self.stop.wait(self.args.status_every_s):
            self._publish_status()

    def _connect(self) -> bool:
        """The environment loop; a bridge's environment once the bridge is there. False: stopped."""
        c = self.config
        while self.env is None:
            if not self._bridge_present():
                return False
            try:
                client = client_name(f"actor {self.actor_id}", self.args.run_id)
                source = envs.source_for(c.env.task)
                self.env = source.make_remote(c.env, self.session, self.args.bridge, client)
            except envs.EnvUnavailable as err:
                self.log.every("bridge", 10.0, f"waiting for bridge {self.args.bridge}: {err}")
        self.loop = EnvLoop(self.env, self.writer, c.env.time_limit)
        return True

    def _bridge_present(self) -> bool:
        """Wait while the bridge is gone (no transitions meanwhile); False if stopped first."""
        if self.bridge is None or self.bridge.present:
            return True
        self.log(f"bridge {self.args.bridge} is not there: collection paused")
        if not self.bridge.wait(lambda: bool(self.stop)):
            return False
        self.log(f"bridge {self.args.bridge} is there: collecting, from a new episode")
        return True

    def _act(self) -> None:
        w = self.writer
        while not self.stop:
            if w.replay_done:  # the run's step budget is reached: wait for the stop
                self.stop.wait(0.2)
                continue
            w.wait_for_replay()
            if self.stop or not self._bridge_present():
                return
            try:
                self._episode()
            except envs.EnvUnavailable as err:  # gone, or refusing: the episode is abandoned
                self._note_fault()
                self._paused(err)
                self.stop.wait(PAUSE_S)
            except envs.EnvFault as err:  # this episode cannot go on; a reset starts a sound one
                self.env_faults += 1
                self.log.every("fault", 10.0, f"episode abandoned ({self.env_faults} so far): {err}")

    def _paused(self, err: envs.EnvUnavailable) -> None:
        """Say why collection pauses: a bridge another client holds once per holder (the refusal
        names how long ago it was heard, which every retry changes), anything else every 10 s."""
        if not isinstance(err, BridgeHeld):
            self.log.every("unavailable", 10.0, f"environment unavailable, collection paused: {err}")
        elif err.holder != self._held_by:
            self.log(f"collection paused until the gripper is free: {err}")
        self._held_by = err.holder if isinstance(err, BridgeHeld) else None

    def _await_first_weights(self) -> bool:
        """Wait for the learner's weights before the first policy step: the actor's own networks
        are not the run's (its seed is its own), and the first policy steps act with the learner's
        initial policy in `nasa train` and the reference. Later weights never hold acting up.
        False: the episode cannot go on (stop, budget, the replay gone)."""
        w = self.writer
        self.log("warm-up over: waiting for the learner's weights before the first policy step")
        while not self.weights.maybe_load():
            if self.stop or w.replay_done or w.broken:
                return False
            if self.bridge is not None and not self.bridge.present:
                return False
            self.stop.wait(WEIGHTS_POLL_S)
        return True

    def _episode(self) -> None:
        """One episode, until its end, a stop, the replay's or the bridge's loss, or the budget."""
        c, w, loop = self.config, self.writer, self.loop
        ts = loop.reset()
        self._held_by = None  # the gripper is this actor's: a client that takes it later is said again
        self._note_fault()
        while not self.stop and not w.replay_done and not w.broken:
            if self.bridge is not None and not self.bridge.present:
                return  # the bridge went: nothing more of this episode is sent
            self.weights.maybe_load()
            warming_up = max(w.steps_at_least, self.weights.env_steps) < c.warmup_steps
            if (not warming_up and self.weights.version is None and not self.args.act_before_weights
                    and not self._await_first_weights()):
                return
            action = collect_action(self.agent, ts.obs, warming_up, self.rng, loop.env.spec.action_dim)
            ts = loop.step(action, self.policy_version)
            self.step_times.observe(loop.last_step_s)
            self._note_fault()
            if ts.last:
                self.episodes += 1
                self._finished.append([loop.episode_return, loop.episode_length])
                return


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: ActorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        run = run_config.join(args.config, session, wire.Keys(args.run_id), stop)
        ActorService(args, session, stop, run).run()

    run_service(ActorArgs, argv, "python -m services.actor", run, check_args)


def check_args(args: ActorArgs) -> None:
    """The actor's flags that its parser cannot check (exit 2 before it connects, not a traceback
    that its supervisor would restart in a loop)."""
    from shared.device import resolve_device

    resolve_device(args.actor_device)
    if not -1 <= args.actor_id < MAX_ACTOR_ID:
        raise ConfigError(f"--actor-id must be -1 (a random one) or in [0, {MAX_ACTOR_ID}), "
                          f"got {args.actor_id}")
    for name in ("send_batch", "max_in_flight", "threads"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not (math.isfinite(args.status_every_s) and args.status_every_s > 0):
        raise ConfigError(f"--status-every-s must be a finite number > 0, got {args.status_every_s}")
