"""Safety interlocks between any client and the finger servos, enforced whatever a client sends.

`SafeFingers` wraps a `ServoBus`:
- goals are clamped to each servo's configured range and to a maximum change per step;
- a step whose bus work outlasts its timeout is reported as truncated;
- hardware error bits (overload, overheating, voltage) are read at every step, in the same sync
  read as the positions;
- the watchdog (`poll_watchdog`, called periodically by the bridge) holds the present position
  when no command came for `watchdog_hold_s`, and turns torque off after `watchdog_off_s`: the
  XL-320 has no bus watchdog of its own;
- the e-stop is idempotent and always wins: it sets its flag before it waits for the bus, every
  bus write checks the flag under the bus lock, so a step in flight never writes after it; steps
  are refused until `rearm()`;
- a servo fault (no reply, error bits) runs the recovery sequence: reboot the faulty servos,
  restore their limits, torque on, home; if homing fails, torque off and wait for an operator
  (`rearm()`). The state is in `status()` for the bridge to publish. One recovery runs at a time:
  a faulted step's and a re-arm's (or two re-arms') would reboot, arm and home the same servos
  at once, and whichever ended last would set the state over what the other did to the servos;
  the second waits for the first, then runs its own.

The e-stop flag is the one source of truth for `estop`: `state` reads it first, so no recovery
that finishes, fails or starts around a racing e-stop can report anything else while it holds.
The flag, the other states and the fault change together under one small lock that is never
held across bus work (`_flags`), so `status()` is one consistent snapshot, and e-stops and
re-arms take effect in the order they are made. Locks are taken in one order: the recovery's
(`_recovery`), then the bus's (`_lock`), then `_flags`; the e-stop never waits for a recovery.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from services.robot_bridge.config import SafetyConfig, ServoConfig
from services.robot_bridge.dynamixel import BusError, ServoBus, ServoState
from services.robot_bridge.states import State

TORQUE_CUT_WAIT_S = 5.0


class Watchdog(StrEnum):
    ACTIVE = "active"
    HOLDING = "holding"
    TORQUE_OFF = "torque_off"


class Refused(RuntimeError):
    """A command the bridge will not carry out now (e-stop, fault, watchdog); the episode ends."""


@dataclass(frozen=True)
class StepReport:
    goals: np.ndarray  # the goals sent, after clamping (steps)
    clamped: bool
    state: ServoState | None  # None when the step ended in a fault
    latency_s: float
    truncated: bool
    reason: str  # why it was truncated ("" when it was not)


class SafeFingers:
    """The four finger servos behind every interlock."""

    def __init__(
        self,
        bus: ServoBus,
        servos: ServoConfig,
        safety: SafetyConfig,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.bus = bus
        self.ids = tuple(servos.ids)
        self.servos = servos
        self.safety = safety
        self._clock = clock
        self._sleep = sleep
        self._low = np.array(servos.min_step, dtype=np.int64)
        self._high = np.array(servos.max_step, dtype=np.int64)
        self.home = np.array(servos.home, dtype=np.int64)
        self._lock = threading.RLock()
        self._estop = threading.Event()
        self._torque_cut = threading.Event()  # set once an e-stop's torque-off has gone out
        self._flags = threading.Lock()  # the e-stop flag, state and fault change together under it
        self._recovery = threading.Lock()  # held for a whole recovery: one at a time
        self._state = State.READY  # what holds when the e-stop flag is clear
        self.watchdog = Watchdog.ACTIVE
        self.fault = ""
        self.fault_servos: tuple[int, ...] = ()
        self.recoveries = 0
        self.last_goals = self.home.copy()
        self.last_errors: dict[int, list[str]] = {}
        self._last_command = clock()
        self._unreached: list[int] = []  # servos a torque-off while waiting for the operator missed

    # -- commands ------------------------------------------------------------------------------
    def action_to_goals(self, action: np.ndarray) -> np.ndarray:
        """An action in [-1, 1]^4 as goal positions over each servo's configured range."""
        a = np.clip(np.nan_to_num(np.asarray(action, dtype=np.float64), nan=0.0), -1.0, 1.0)
        return np.rint(self._low + (a + 1.0) * 0.5 * (self._high - self._low)).astype(np.int64)

    def clamp(self, goals: np.ndarray) -> tuple[np.ndarray, bool]:
        """Goals within each servo's range and within max_step_change of the previous goals."""
        wanted = np.asarray(goals, dtype=np.int64)
        step = self.servos.max_step_change
        safe = np.clip(wanted, self._low, self._high)
        safe = np.clip(safe, self.last_goals - step, self.last_goals + step)
        return safe, bool(np.any(safe != wanted))

    def arm(self) -> ServoState:
        """Limits set, torque on, goals at the present positions (no jump): ready for homing. Only
        a ready gripper: one waiting for its operator is re-armed by the operator (`rearm`)."""
        with self._lock:
            self._refuse_if_stopped()
            if self.state is not State.READY:
                raise Refused(f"the bridge is {self.state.value}: {self.fault}")
            return self._arm()

    def _arm(self) -> ServoState:
        with self._lock:
            self._refuse_if_stopped()
            for sid in self.ids:
                self.bus.set_limits(sid, self.servos.moving_speed, self.servos.torque_limit)
            state = self.bus.read_state(self.ids)
            self.last_goals = state.position.copy()
            self.bus.write_goals(dict(zip(self.ids, self.last_goals.tolist(), strict=True)))
            self.bus.set_torque(True, self.ids)
            self.watchdog = Watchdog.ACTIVE
            self._last_command = self._clock()
            return state

    def go_home(self) -> bool:
        """Move home in steps no bigger than max_step_change; True when within tolerance."""
        end = self._clock() + self.safety.home_timeout_s
        while self._clock() < end:
            with self._lock:
                self._refuse_if_stopped()
                goals, _ = self.clamp(self.home)
                self._send(goals)
                state = self.bus.read_state(self.ids)
            if np.all(np.abs(state.position - self.home) <= self.safety.home_tolerance):
                return True
            self._sleep(0.05)
        return False

    def step(self, action: np.ndarray, settle_s: float = 0.0) -> StepReport:
        """Send clamped goals, let them act for `settle_s`, read the state and its error bits."""
        start = self._clock()
        try:
            with self._lock:
                self._refuse_if_stopped()
                if self.state is not State.READY:
                    raise Refused(f"the bridge is {self.state.value}: {self.fault}")
                if self.watchdog is Watchdog.TORQUE_OFF:
                    raise Refused("the watchdog turned torque off: reset first")
                goals, clamped = self.clamp(self.action_to_goals(action))
                self._send(goals)  # the first bus work: goals are set by any BusError below
            self._wait(settle_s)
            with self._lock:
                self._refuse_if_stopped()
                state = self.bus.read_state(self.ids)
        except BusError as e:
            # Recovered with the bus lock released: a re-arm's recovery under way needs it to finish.
            return self._faulted(goals, clamped, start, e.servo_ids, str(e))
        self.last_errors = state.faults(self.ids)
        if self.last_errors:
            faulty = tuple(self.last_errors)
            return self._faulted(goals, clamped, start, faulty, f"hardware error: {self.last_errors}")
        latency = self._clock() - start
        late = latency > self.safety.step_timeout_s
        reason = f"step took {latency:.3f} s, over its {self.safety.step_timeout_s} s timeout" if late else ""
        return StepReport(goals, clamped, state, latency, late, reason)

    # -- e-stop --------------------------------------------------------------------------------
    def estop(self) -> list[int]:
        """Torque off and refuse steps until `rearm()`; safe to call from any thread, any number of times.
        Returns the servos the torque-off did not reach."""
        with self._flags:
            self._estop.set()  # first: a step in flight sees it before its next bus write
        with self._lock:
            unreached = self._torque_off()
            if unreached:
                # A servo that cannot hear the torque-off is a fault an operator must see.
                self._set(fault=f"e-stop could not reach servos {unreached}", servos=tuple(unreached))
        self._torque_cut.set()
        return unreached

    def wait_torque_cut(self, timeout_s: float = TORQUE_CUT_WAIT_S) -> bool:
        """After a refusal: wait until the e-stop's torque-off has gone out (call without the bus lock),
        so a client never hears of the e-stop before the servos do."""
        return not self.estopped or self._torque_cut.wait(timeout=timeout_s)

    @property
    def bus_lock(self) -> threading.RLock:
        """Held for every bus transfer: whoever else uses the bus (valve servo, angle) takes it too."""
        return self._lock

    @property
    def estopped(self) -> bool:
        return self._estop.is_set()

    @property
    def state(self) -> State:
        with self._flags:
            return State.ESTOP if self._estop.is_set() else self._state

    def rearm(self) -> None:
        """The operator's explicit re-arm after an e-stop or a failed recovery: recover and home."""
        self.release()
        self.recover()

    def release(self) -> None:
        """The re-arm's first half, at once: the e-stop is cleared and the state is `recovering`
        (never `ready` before the homing). A caller that runs `recover()` on another thread calls
        this on its own, so an e-stop made after the re-arm always wins over it."""
        with self._flags:
            self._state = State.RECOVERING
            self._estop.clear()
            self._torque_cut.clear()

    def recover(self) -> None:
        """The re-arm's second half: reboot the faulty servos, arm, home (an e-stop made meanwhile
        stops it, and stays). A recovery under way (a faulted step's, another re-arm's) ends first."""
        self._recover()

    # -- watchdog ------------------------------------------------------------------------------
    def touch(self) -> None:
        """The bridge is busy on the gripper's behalf (a valve reset): not an idle client."""
        self._last_command = self._clock()

    def poll_watchdog(self) -> Watchdog:
        """Hold, then torque off, when no command came for too long; call it periodically."""
        idle = self._clock() - self._last_command
        with self._lock:
            if self.state is State.WAITING_FOR_OPERATOR and self._unreached:
                self._unreached = self._torque_off()
            if self.estopped or self.state is not State.READY:
                return self.watchdog
            try:
                if idle >= self.safety.watchdog_off_s and self.watchdog is not Watchdog.TORQUE_OFF:
                    self.watchdog = Watchdog.TORQUE_OFF
                    unreached = self._torque_off()
                    if unreached:
                        raise BusError(f"watchdog could not turn torque off on {unreached}", unreached)
                elif idle >= self.safety.watchdog_hold_s and self.watchdog is Watchdog.ACTIVE:
                    present = self.bus.read_state(self.ids).position
                    self.bus.write_goals(dict(zip(self.ids, present.tolist(), strict=True)))
                    self.last_goals = present.copy()
                    self.watchdog = Watchdog.HOLDING
            except BusError as e:
                self._set(State.WAITING_FOR_OPERATOR, str(e), e.servo_ids)
        return self.watchdog

    # -- status --------------------------------------------------------------------------------
    def status(self) -> dict:
        """One consistent snapshot: the state with the fault it goes with."""
        with self._flags:
            return {
                "state": (State.ESTOP if self._estop.is_set() else self._state).value,
                "watchdog": self.watchdog.value,
                "fault": self.fault,
                "fault_servos": list(self.fault_servos),
                "recoveries": self.recoveries,
                "errors": {str(k): v for k, v in self.last_errors.items()},
            }

    def _set(self, state: State | None = None, fault: str | None = None,
             servos: tuple[int, ...] | None = None) -> None:
        """Change the state (under an e-stop it shows once the e-stop is released) and the fault
        together."""
        with self._flags:
            if state is not None:
                self._state = state
            if fault is not None:
                self.fault = fault
            if servos is not None:
                self.fault_servos = tuple(servos)

    # -- internals -----------------------------------------------------------------------------
    def _refuse_if_stopped(self) -> None:
        if self.estopped:
            raise Refused("e-stop: torque is off until the bridge is re-armed")

    def _send(self, goals: np.ndarray) -> None:
        self.bus.write_goals(dict(zip(self.ids, goals.tolist(), strict=True)))
        self.last_goals = goals.copy()
        self._last_command = self._clock()
        if self.watchdog is Watchdog.HOLDING:
            self.watchdog = Watchdog.ACTIVE

    def _wait(self, seconds: float) -> None:
        """Sleep in short slices so an e-stop during the wait ends the step at once."""
        end = self._clock() + seconds
        while (left := end - self._clock()) > 0:
            if self.estopped:
                raise Refused("e-stop during the step")
            self._sleep(min(left, 0.01))

    def _faulted(self, goals: np.ndarray, clamped: bool, start: float, servo_ids, reason: str) -> StepReport:
        self._recover((reason, tuple(servo_ids)))
        return StepReport(goals, clamped, None, self._clock() - start, True, reason)

    def _recover(self, fault: tuple[str, tuple[int, ...]] | None = None) -> None:
        """Reboot the faulty servos (if any), restore limits, torque on, home; else wait for an operator.

        `fault` is a faulted step's reason and servos; without it (a re-arm) the standing fault's
        servos are rebooted. Called without the bus lock: it waits for a recovery under way."""
        with self._recovery:
            if fault is None:
                self._set(State.RECOVERING)  # a recovery that ended meanwhile may have said `ready`
            else:
                self._set(State.RECOVERING, *fault)
            self._recover_now(self.fault_servos)

    def _recover_now(self, servo_ids: tuple[int, ...]) -> None:
        self.recoveries += 1
        try:
            with self._lock:
                for sid in servo_ids:
                    self.bus.reboot(sid, self.safety.reboot_wait_s)
                self._arm()
            homed = self.go_home()
        except (BusError, Refused) as e:
            homed = False
            self._set(fault=f"{self.fault}; recovery failed: {e}")
        if homed:
            self._set(State.READY, "", ())
            return
        # Under an e-stop the state shows `estop` until the re-arm, which starts a recovery anew.
        self._set(State.WAITING_FOR_OPERATOR)
        with self._lock:
            # A servo that cannot hear it is the fault already reported; the watchdog tells it
            # again until it does (a cable that comes back would leave it holding torque).
            self._unreached = self._torque_off()

    def _torque_off(self) -> list[int]:
        """Torque off on every servo of the bus that answers (the valve's too: a turn cut short
        may have left it on), one by one; returns those that did not."""
        unreached = []
        for sid in dict.fromkeys((*self.ids, *getattr(self.bus, "ids", ()))):
            try:
                self.bus.set_torque(False, [sid])
            except BusError:
                unreached.append(sid)
        return unreached
