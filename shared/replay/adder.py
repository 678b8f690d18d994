"""The replay's writing side: an environment loop hands each step to an `Adder`.

- `StoreAdder`: straight into a ReplayStore in this process (`nasa train`).
- `ZenohWriter`: the actor's adder. Steps are sent in batches of `send_batch`
  transitions (fewer at an episode end) as `TransitionBatch`es: each new frame
  once, delta-coded and zstd-compressed, on a publisher with congestion control
  BLOCK. At most `max_in_flight` batches wait for the replay's acknowledgement;
  when the replay's rate limiter holds inserts back, `add` waits
  (backpressure). The writer watches the replay's liveliness token: when it
  goes, the unacknowledged batches count as lost and the episode under way is
  `broken` (the loop abandons it; the replay never stitches across a gap).
  A batch the replay refuses is acknowledged with the reason: the writer counts
  it, logs each reason once, and stops its actor (`refused_for_good`) when the
  replay says it will refuse every batch of this incarnation.

Both store every row unscored (intrinsic NaN): scoring is the scorer's business.
The in-flight accounting is `SendWindow`, plain Python with no Zenoh.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import numpy as np

from shared import wire

if TYPE_CHECKING:
    from shared.replay.store import ReplayStore
    from shared.service import Log, StopFlag

SEND_BATCH = 8
"""An actor's transitions per message, unless told otherwise."""
ACK_TIMEOUT_S = 60.0
"""No acknowledgement for this long while the window is full: the replay restarted and lost them."""
REFUSALS_TO_STOP = 3
"""Refusals the replay calls lasting, with nothing stored between them, before a writer stops its actor."""
MAX_REASONS_LOGGED = 32
"""Distinct refusal reasons a writer logs (each once)."""


class Adder(Protocol):
    def add_first(self, frame: np.ndarray) -> None:
        """Begin an episode with its reset frame."""
        ...

    def add(self, action: np.ndarray, reward: float, discount: float, frame: np.ndarray,
            last: bool, policy_version: int) -> None:
        """One transition: the action taken, its reward and stored discount, the next frame."""
        ...


class StoreAdder:
    """Adds to a ReplayStore in this process; `last_index` is the global index of the newest row."""

    def __init__(self, store: ReplayStore) -> None:
        self.store = store
        self.last_index = -1
        self._episode: int | None = None

    def add_first(self, frame: np.ndarray) -> None:
        self._episode = self.store.begin_episode(frame)

    def add(self, action: np.ndarray, reward: float, discount: float, frame: np.ndarray,
            last: bool, policy_version: int) -> None:
        if self._episode is None:
            raise RuntimeError("add() before add_first(): an episode begins with its reset frame")
        self.last_index = self.store.add(
            self._episode, action, reward, discount, frame, last, policy_version=policy_version
        )
        if last:
            self._episode = None


class SendWindow:
    """A writer's flow control: batches in flight, acknowledgements, the replay's presence.

    Thread-safe: Zenoh callbacks call on_ack / on_replay / observe while the loop's
    thread blocks in acquire / wait_alive. `clock` and `poll_s` are for tests.
    """

    def __init__(self, max_in_flight: int, log: Callable[[str], None] = print,
                 ack_timeout_s: float = ACK_TIMEOUT_S, poll_s: float = 0.5,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be >= 1, got {max_in_flight}")
        self.max_in_flight = max_in_flight
        self.log = log
        self.ack_timeout_s = ack_timeout_s
        self.poll_s = poll_s
        self.clock = clock
        self.in_flight = 0
        self.alive = False  # the replay's liveliness token is present
        self.was_lost = False  # the replay has gone away at least once
        self.broken = False  # the replay went away during the episode under way
        self.global_steps = 0  # newest replay count seen (acks, stats)
        self.acked_steps = 0  # newest replay count an ack of ours carried
        self.replay_done = False
        self.lost = 0  # batches counted lost (replay gone, or never acknowledged)
        self._sizes: deque[int] = deque()  # transitions of each batch in flight, oldest first
        self._cv = threading.Condition()

    def acquire(self, stop: StopFlag, steps: int = 1) -> bool:
        """Wait until one more batch (of `steps` transitions) may be in flight and count it; False
        (nothing counted) if stop is set or the episode is broken: that batch must not be sent."""
        with self._cv:
            waited, seen = self.clock(), self.global_steps
            while self.in_flight >= self.max_in_flight and not stop and not self.broken:
                self._cv.wait(self.poll_s)
                if self.clock() - waited <= self.ack_timeout_s:
                    continue
                if self.alive and self.global_steps == seen:
                    # The replay acknowledges every batch it takes, stored or refused; one that has
                    # stored nothing since is holding ours (its rate limiter waits on the learner,
                    # or it cannot write): sending more would only queue them there.
                    self.log(f"no acknowledgement for {self.ack_timeout_s:.0f} s, and the replay has "
                             "stored nothing since: waiting on it")
                    waited = self.clock()
                    continue
                self.log(f"no acknowledgement for {self.ack_timeout_s:.0f} s: "
                         f"assuming the {self.in_flight} in-flight batches lost")
                self._lose()
            if stop or self.broken:
                return False
            self.in_flight += 1
            self._sizes.append(steps)
            return True

    def _lose(self) -> None:
        """Under the lock: the batches in flight will never be acknowledged."""
        self.lost += self.in_flight
        self.in_flight = 0
        self._sizes.clear()

    @property
    def steps_at_least(self) -> int:
        """The replay's count once the batches in flight land: the newest count an ack carried
        plus the transitions sent since, which it does not hold yet (or a newer count seen in its
        stats, which other actors' inserts may have passed). Exact for a lone actor, whatever
        the acks' delay."""
        with self._cv:
            return max(self.global_steps, self.acked_steps + sum(self._sizes))

    def on_ack(self, num_inserted: int) -> None:
        with self._cv:
            self.in_flight = max(0, self.in_flight - 1)
            if self._sizes:  # the replay takes one actor's batches in the order they were sent
                self._sizes.popleft()
            self.global_steps = max(self.global_steps, num_inserted)
            self.acked_steps = max(self.acked_steps, num_inserted)
            self._cv.notify_all()

    def on_replay(self, alive: bool) -> None:
        """The replay's liveliness token appeared (alive) or went away."""
        with self._cv:
            was_alive, self.alive = self.alive, alive
            if not alive:
                # Never acknowledged: the replay did not store them, or its acks were lost.
                self._lose()
                self.broken = True
                if was_alive:
                    self.was_lost = True
                    self.log("the replay is gone: pausing, and abandoning the episode under way")
            elif not was_alive and self.was_lost:
                self.log("the replay is back: acting again from a new episode")
            self._cv.notify_all()

    def observe(self, num_inserted: int, done: bool | None = None) -> None:
        """A replay count seen elsewhere (replay stats, weights); `done`: the step budget is reached."""
        with self._cv:
            self.global_steps = max(self.global_steps, num_inserted)
            if done is not None:
                self.replay_done = done
            self._cv.notify_all()

    def begin_episode(self) -> None:
        """A new episode starts with its reset frame: the replay accepts it whatever came before,
        if it is there (it may have gone during the reset)."""
        with self._cv:
            self.broken = not self.alive

    def wait_alive(self, stop: StopFlag, what: str = "the replay") -> bool:
        """Block until the replay is alive (True) or stop is set (False)."""
        last_log = None
        with self._cv:
            while not self.alive and not stop:
                now = self.clock()
                if last_log is None or now - last_log >= 10.0:
                    last_log = now
                    self.log(f"waiting for {what}")
                self._cv.wait(self.poll_s)
            return self.alive and not stop

    def wake(self) -> None:
        """Wake every waiter (e.g. when stop was set)."""
        with self._cv:
            self._cv.notify_all()


def transition_batch(actor_id: int, incarnation: int, episode: int, start: int,
                     first: np.ndarray | None, steps: list[tuple], launch: int = 0) -> wire.TransitionBatch:
    """The message of consecutive steps (action, reward, discount, frame, last, policy_version)."""
    actions, rewards, discounts, frames, lasts, versions = zip(*steps, strict=True)
    return wire.TransitionBatch(
        actor_id=actor_id,
        incarnation=incarnation,
        episode=episode,
        start=start,
        n=len(steps),
        frame_shape=list(frames[0].shape),
        frames=wire.encode_frames(np.stack(frames)),
        first_frame=wire.encode_frames(first[None]) if first is not None else None,
        actions=np.asarray(actions, "<f4").tobytes(),
        rewards=np.asarray(rewards, "<f4").tobytes(),
        discounts=np.asarray(discounts, "<f4").tobytes(),
        lasts=np.asarray(lasts, "u1").tobytes(),
        policy_versions=np.asarray(versions, "<i8").tobytes(),
        launch=launch,
    )


class ZenohWriter:
    """The actor's adder over Zenoh (module docstring). A context manager: it declares the
    insert publisher and the ack, stats and replay-liveliness subscribers."""

    def __init__(self, session, keys: wire.Keys, actor_id: int, incarnation: int,
                 frame_shape: tuple[int, int, int], send_batch: int, max_in_flight: int,
                 stop: StopFlag, log: Log, budget: int | None = None, launch: int = 0) -> None:
        self.session, self.keys, self.stop, self.log = session, keys, stop, log
        self.launch = launch  # tells this launch from another that got the same incarnation
        self.budget = budget  # the run's step budget: an ack that reaches it ends the acting
        self.bounds = wire.Bounds(steps=budget)  # and a count far past it is refused
        self.actor_id, self.incarnation = actor_id, incarnation
        self.frame_shape = tuple(frame_shape)
        self.send_batch = max(1, send_batch)
        self.window = SendWindow(max_in_flight, log)
        self.invalid = 0
        self.refused = 0  # batches the replay acknowledged without storing them
        self.refused_for_good: str | None = None  # why, once the replay will never take this incarnation's
        self._lasting_run = 0  # lasting refusals since the last batch stored
        self._reasons_logged: set[str] = set()
        self._episode = -1
        self._start = 0
        self._first: np.ndarray | None = None
        self._steps: list[tuple] = []
        self._declared: list = []
        self._publisher = None

    # -- the adder ---------------------------------------------------------------------------

    @property
    def global_steps(self) -> int:
        return self.window.global_steps

    @property
    def steps_at_least(self) -> int:
        """The replay's count once this writer's transitions land, those it has not sent yet
        too (SendWindow.steps_at_least): what an actor's warm-up reads, so that a lone actor's
        first policy step is the one after `warmup_steps`, as in `nasa train`, and not a few
        later while its acks are on their way."""
        return self.window.steps_at_least + len(self._steps)

    @property
    def replay_done(self) -> bool:
        """The step budget is reached: the replay's stats say so, or an ack's count reached it
        (sooner: stats come every half second, and steps past the budget are dropped)."""
        reached = self.budget is not None and self.window.global_steps >= self.budget
        return self.window.replay_done or reached

    @property
    def broken(self) -> bool:
        return self.window.broken

    def observe(self, num_inserted: int) -> None:
        """A global step count seen elsewhere (the weights' env_steps)."""
        self.window.observe(num_inserted)

    def wait_for_replay(self) -> bool:
        return self.window.wait_alive(self.stop, f"the replay ({self.keys.alive('replay', 0)})")

    def add_first(self, frame: np.ndarray) -> None:
        self._check(frame)
        self.window.begin_episode()
        self._episode += 1
        self._start, self._first, self._steps = 0, frame, []

    def add(self, action: np.ndarray, reward: float, discount: float, frame: np.ndarray,
            last: bool, policy_version: int) -> None:
        if self._episode < 0:
            raise RuntimeError("add() before add_first(): an episode begins with its reset frame")
        self._check(frame)
        self._steps.append((action, reward, discount, frame, last, policy_version))
        if len(self._steps) >= self.send_batch or last:
            self._send()

    def _check(self, frame: np.ndarray) -> None:
        if frame.shape != self.frame_shape or frame.dtype != np.uint8:
            raise ValueError(f"frame {frame.dtype} {frame.shape}, expected uint8 {self.frame_shape}")

    def _send(self) -> None:
        steps, self._steps = self._steps, []
        if not self.window.acquire(self.stop, len(steps)):
            return  # stopping, or the episode is broken: the loop abandons it
        msg = transition_batch(self.actor_id, self.incarnation, self._episode, self._start, self._first,
                               steps, self.launch)
        self._publisher.put(wire.encode(msg))
        self._start += len(steps)
        self._first = None

    # -- Zenoh -------------------------------------------------------------------------------

    def _on_ack(self, sample) -> None:
        try:
            ack = wire.decode(sample.payload.to_bytes(), wire.InsertAck, self.bounds)
        except wire.WireError as err:
            return self._invalid(f"ack: {err}")
        # An ack without a launch (0) is an older replay's, which does not tell launches apart.
        if (ack.actor_id == self.actor_id and ack.incarnation == self.incarnation
                and ack.launch in (0, self.launch)):
            self._on_refusal(ack.refused, ack.lasting)  # first: a writer waiting on this ack sees the stop
            self.window.on_ack(ack.num_inserted)

    def _on_refusal(self, reason: str, lasting: bool) -> None:
        """Count a refused batch and log each reason once; after REFUSALS_TO_STOP lasting refusals
        with nothing stored between them, give up: set `refused_for_good` and stop."""
        if not reason:
            self._lasting_run = 0
            return
        self.refused += 1
        if reason not in self._reasons_logged and len(self._reasons_logged) < MAX_REASONS_LOGGED:
            self._reasons_logged.add(reason)
            self.log(f"the replay refused a batch ({'for good' if lasting else 'this once'}): {reason}")
        if not lasting:  # the batches after a refused episode start are refused as its orphans
            return
        self._lasting_run += 1
        if self._lasting_run >= REFUSALS_TO_STOP and self.refused_for_good is None:
            self.refused_for_good = reason
            self.stop.set(f"the replay refuses every batch of this incarnation: {reason}")

    def _on_stats(self, sample) -> None:
        try:
            stats = wire.decode(sample.payload.to_bytes(), wire.ReplayStats, self.bounds)
        except wire.WireError as err:
            return self._invalid(f"replay stats: {err}")
        self.window.observe(stats.num_inserted, stats.done)

    def _on_replay_alive(self, sample) -> None:
        import zenoh

        self.window.on_replay(sample.kind == zenoh.SampleKind.PUT)

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("writer-invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def __enter__(self) -> ZenohWriter:
        import zenoh

        s, k = self.session, self.keys
        self._publisher = s.declare_publisher(k.insert(self.actor_id),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        self._declared = [
            self._publisher,
            s.declare_subscriber(k.ack(self.actor_id), self._on_ack),
            s.declare_subscriber(k.replay_stats, self._on_stats),
            s.liveliness().declare_subscriber(k.alive("replay", 0), self._on_replay_alive, history=True),
        ]
        return self

    def __exit__(self, *exc: object) -> None:
        self.window.wake()
        for entity in reversed(self._declared):
            entity.undeclare()
        self._declared = []
