"""Every interlock of the bridge, against the emulated bus through the real dynamixel-sdk."""

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from services.robot_bridge import xl320
from services.robot_bridge.config import SafetyConfig, ServoConfig
from services.robot_bridge.dynamixel import BusError, ServoBus
from services.robot_bridge.emulator import BusEmulator
from services.robot_bridge.safety import Refused, SafeFingers, State, Watchdog
from tests.test_robot_bridge_bus import LATENCY_MS, wait_until

IDS = (1, 2, 3, 4)
HOME = (512, 600, 512, 600)
SERVOS = ServoConfig(ids=IDS, min_step=(200,) * 4, max_step=(820,) * 4, home=HOME, moving_speed=600,
                     torque_limit=700, max_step_change=50)
SAFETY = SafetyConfig(step_timeout_s=5.0, watchdog_hold_s=1.0, watchdog_off_s=3.0, home_tolerance=3,
                      home_timeout_s=10.0, reboot_wait_s=0.0)


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def emu() -> Iterator[BusEmulator]:
    with BusEmulator(IDS, positions=dict(zip(IDS, HOME, strict=True))) as emulator:
        yield emulator


def fingers(emu: BusEmulator, **kwargs) -> SafeFingers:
    bus = ServoBus(emu.port, 1000000, IDS, latency_ms=LATENCY_MS)
    f = SafeFingers(bus, SERVOS, kwargs.pop("safety", SAFETY), **kwargs)
    f.arm()
    assert f.go_home()
    return f


def torque(emu: BusEmulator) -> list[int]:
    return [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in IDS]


def test_out_of_range_and_too_fast_goals_are_clamped(emu) -> None:
    f = fingers(emu)
    goals, clamped = f.clamp(np.array([2000, -5, 530, 512]))
    assert clamped and list(goals) == [562, 550, 530, 550]  # range first, then +-50 from the last goal
    report = f.step(np.array([1.0, -1.0, 0.0, 0.2903]))
    assert report.clamped and not report.truncated
    assert list(report.goals) == [562, 550, 510, 600]
    assert [emu.snapshot(sid, xl320.GOAL_POSITION) for sid in IDS] == [562, 550, 510, 600]
    report = f.step(np.array([1.0, -1.0, 0.0, 0.2903]))
    assert list(report.goals) == [612, 500, 510, 600]  # each step may move 50 more
    f.bus.close()


def test_a_slow_step_is_truncated_and_reported(emu) -> None:
    safety = SafetyConfig(**{**SAFETY.__dict__, "step_timeout_s": 0.01})
    f = fingers(emu, safety=safety)
    report = f.step(np.zeros(4), settle_s=0.05)
    assert report.truncated and "timeout" in report.reason and report.state is not None
    f.bus.close()


def test_the_watchdog_holds_then_turns_torque_off(emu) -> None:
    clock = FakeClock()
    f = fingers(emu, clock=clock)
    f.step(np.full(4, 0.3))  # goals 50 steps away: the servos are moving
    clock.now += 0.5
    assert f.poll_watchdog() is Watchdog.ACTIVE
    clock.now += 0.6
    assert f.poll_watchdog() is Watchdog.HOLDING
    # The hold is a sync write (no reply): wait for the emulator to have taken it off the line.
    wait_until(lambda: [emu.snapshot(sid, xl320.GOAL_POSITION) for sid in IDS] == list(f.last_goals))
    clock.now += 2.0
    assert f.poll_watchdog() is Watchdog.TORQUE_OFF
    assert torque(emu) == [0, 0, 0, 0]
    with pytest.raises(Refused, match="watchdog"):
        f.step(np.zeros(4))
    f.arm()  # what a reset does first
    assert torque(emu) == [1, 1, 1, 1] and f.watchdog is Watchdog.ACTIVE
    f.bus.close()


def test_estop_wins_over_a_step_in_flight_and_holds_until_rearmed(emu) -> None:
    f = fingers(emu)
    outcome: list[BaseException | object] = []

    def step() -> None:
        try:
            outcome.append(f.step(np.full(4, 0.3), settle_s=60.0))
        except Refused as e:
            outcome.append(e)

    thread = threading.Thread(target=step)
    thread.start()
    wait_until(lambda: emu.snapshot(1, xl320.GOAL_POSITION) != HOME[0])  # the step is in flight
    f.estop()
    thread.join(timeout=30)
    assert not thread.is_alive()
    assert isinstance(outcome[0], Refused)
    assert torque(emu) == [0, 0, 0, 0] and f.status()["state"] == "estop"
    f.estop()  # idempotent
    with pytest.raises(Refused, match="e-stop"):
        f.step(np.zeros(4))
    assert torque(emu) == [0, 0, 0, 0]
    f.rearm()
    assert f.state is State.READY and torque(emu) == [1, 1, 1, 1]
    assert not f.step(np.zeros(4)).truncated
    f.bus.close()


def test_a_servo_fault_is_recovered_by_reboot_and_homing(emu) -> None:
    f = fingers(emu)
    emu.overload(3)
    report = f.step(np.zeros(4))
    assert report.truncated and "overload" in report.reason
    assert emu.servos[3].reboots == 1
    status = f.status()
    assert status["state"] == "ready" and status["recoveries"] == 1 and status["fault"] == ""
    assert torque(emu) == [1, 1, 1, 1]
    assert emu.snapshot(3, xl320.HARDWARE_ERROR_STATUS) == 0
    assert not f.step(np.zeros(4)).truncated
    f.bus.close()


def test_a_failed_recovery_waits_for_the_operator(emu) -> None:
    f = fingers(emu)
    emu.kill(2)
    report = f.step(np.zeros(4))
    assert report.truncated and "[2]" in report.reason
    status = f.status()
    assert status["state"] == "waiting_for_operator" and status["fault_servos"] == [2]
    assert "recovery failed" in status["fault"]
    with pytest.raises(Refused, match="waiting_for_operator"):
        f.step(np.zeros(4))
    assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in (1, 3, 4)] == [0, 0, 0]
    emu.kill(2, dead=False)  # the operator fixed the cable
    f.rearm()
    assert f.status()["state"] == "ready" and torque(emu) == [1, 1, 1, 1]
    f.bus.close()


def test_a_racing_estop_is_the_state_while_a_faulted_step_recovers_and_after(emu) -> None:
    f = fingers(emu)
    write_goals, in_write, go_on = f.bus.write_goals, threading.Event(), threading.Event()

    def failing_write(goals: dict[int, int]) -> None:  # the bus fails while the e-stop comes in
        in_write.set()
        go_on.wait()
        raise BusError("servo 2: sync write failed", [2])

    f.bus.write_goals = failing_write
    stepping = threading.Thread(target=f.step, args=(np.zeros(4),))
    stepping.start()
    in_write.wait()
    stopping = threading.Thread(target=f.estop)  # waits for the bus, held by the step
    stopping.start()
    wait_until(lambda: f.estopped)
    assert f.status()["state"] == "estop"
    f.bus.write_goals = write_goals
    go_on.set()  # the step's fault now starts a recovery, which the e-stop refuses
    stepping.join()
    stopping.join()
    status = f.status()
    assert status["state"] == "estop" and f.state is State.ESTOP  # not `recovering`
    assert torque(emu) == [0, 0, 0, 0]
    with pytest.raises(Refused, match="e-stop"):
        f.step(np.zeros(4))
    f.rearm()
    assert f.status()["state"] == "ready" and torque(emu) == [1, 1, 1, 1]
    f.bus.close()


def test_status_never_says_ready_while_a_rearm_has_not_homed(emu) -> None:
    f = fingers(emu)
    f.estop()
    set_limits, in_arm, go_on = f.bus.set_limits, threading.Event(), threading.Event()
    seen: list[str] = []

    def slow_limits(servo_id: int, moving_speed: int, torque_limit: int) -> None:
        if not in_arm.is_set():
            seen.append(f.status()["state"])
            in_arm.set()
            go_on.wait()
        set_limits(servo_id, moving_speed, torque_limit)

    f.bus.set_limits = slow_limits
    rearming = threading.Thread(target=f.rearm)
    rearming.start()
    in_arm.wait()
    assert f.status()["state"] == "recovering" and seen == ["recovering"]
    stopping = threading.Thread(target=f.estop)  # the operator changed their mind: it wins
    stopping.start()
    wait_until(lambda: f.estopped)  # its torque-off waits for the bus, held by the re-arm
    assert f.status()["state"] == "estop"
    go_on.set()
    rearming.join()
    stopping.join()
    assert f.status()["state"] == "estop" and torque(emu) == [0, 0, 0, 0]
    f.bus.close()


class SignallingLock:
    """A lock that says when a thread finds it held and has to wait for it."""

    def __init__(self, waiting: threading.Event) -> None:
        self._lock = threading.Lock()
        self._waiting = waiting

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if self._lock.acquire(blocking=False):
            return True
        self._waiting.set()
        return self._lock.acquire(blocking, timeout)

    def release(self) -> None:
        self._lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class Gate:
    """An injected sleep that parks the first call from a chosen thread until the test opens it;
    every other call sleeps as asked (the homing loop's pace)."""

    def __init__(self) -> None:
        self.thread: threading.Thread | None = None
        self.parked = threading.Event()
        self.open = threading.Event()

    def __call__(self, seconds: float) -> None:
        if threading.current_thread() is self.thread and not self.parked.is_set():
            self.parked.set()
            self.open.wait()
            return
        time.sleep(seconds)


def away_from_home(f: SafeFingers, emu: BusEmulator) -> None:
    """A step that leaves every finger 50 steps from home, so a homing takes several rounds."""
    goals = list(f.step(np.full(4, 0.3)).goals)
    wait_until(lambda: [emu.snapshot(sid, xl320.PRESENT_POSITION) for sid in IDS] == goals)


def gated_fingers(emu: BusEmulator) -> tuple[SafeFingers, dict[str, Gate], threading.Event]:
    """Fingers away from home whose waits park at the gate of their thread ("step", "rearm"), and
    whose recovery lock sets the event when a second recovery comes to wait on it."""
    gates = {"step": Gate(), "rearm": Gate()}
    f = fingers(emu, sleep=lambda s: gates[threading.current_thread().name](s)
                if threading.current_thread().name in gates else time.sleep(s))
    away_from_home(f, emu)
    waiting = threading.Event()
    f._recovery = SignallingLock(waiting)
    return f, gates, waiting


def test_a_rearm_waits_for_the_recovery_a_faulted_step_started(emu) -> None:
    f, gates, waiting = gated_fingers(emu)
    touched: list[str] = []  # who rebooted or armed a servo, in order
    reboot, set_limits = f.bus.reboot, f.bus.set_limits

    def logged_reboot(servo_id: int, wait_s: float = 0.5) -> None:
        touched.append(f"{threading.current_thread().name}: reboot {servo_id}")
        waiting.set()  # the re-arm reached the bus: it did not wait
        reboot(servo_id, wait_s)

    def logged_limits(servo_id: int, moving_speed: int, torque_limit: int) -> None:
        touched.append(f"{threading.current_thread().name}: arm {servo_id}")
        waiting.set()
        set_limits(servo_id, moving_speed, torque_limit)

    f.bus.reboot, f.bus.set_limits = logged_reboot, logged_limits
    emu.overload(3)
    stepping = threading.Thread(target=f.step, args=(np.full(4, 0.3),), name="step", daemon=True)
    gates["step"].thread = stepping
    stepping.start()
    try:
        assert gates["step"].parked.wait(30)  # the step's recovery is homing
        assert f.status()["state"] == "recovering"
        step_work = list(touched)
        assert step_work[0] == "step: reboot 3"
        rearming = threading.Thread(target=f.rearm, name="rearm", daemon=True)
        rearming.start()
        assert waiting.wait(30)
        assert touched == step_work, "the re-arm's recovery ran during the step's"
    finally:
        gates["step"].open.set()
    stepping.join(30)
    rearming.join(30)
    assert not stepping.is_alive() and not rearming.is_alive()
    rearm_work = touched[len(step_work):]
    assert rearm_work and all(t.startswith("rearm: arm") for t in rearm_work)  # after, and nothing to reboot
    status = f.status()
    assert status["state"] == "ready" and status["recoveries"] == 2 and emu.servos[3].reboots == 1
    assert torque(emu) == [1, 1, 1, 1]
    assert not f.step(np.zeros(4)).truncated
    f.bus.close()


def test_a_step_that_faults_during_a_rearm_recovers_after_it_without_holding_the_bus(emu) -> None:
    f, gates, waiting = gated_fingers(emu)
    read_state = f.bus.read_state

    def failing_read(ids=None):  # noqa: ANN001, ANN202
        if threading.current_thread().name == "step" and not getattr(failing_read, "done", False):
            failing_read.done = True
            raise BusError("sync read failed; servos not answering: [2]", [2])
        return read_state(ids)

    f.bus.read_state = failing_read
    stepping = threading.Thread(target=f.step, args=(np.full(4, 0.3), 1.0), name="step", daemon=True)
    gates["step"].thread = stepping
    stepping.start()
    try:
        assert gates["step"].parked.wait(30)  # the step is in flight, its goals sent
        rearming = threading.Thread(target=f.rearm, name="rearm", daemon=True)
        gates["rearm"].thread = rearming
        rearming.start()
        assert gates["rearm"].parked.wait(30)  # the re-arm's recovery is homing
        gates["step"].open.set()  # the step's read fails: its recovery must wait for the re-arm's
        assert waiting.wait(30)
        assert emu.servos[2].reboots == 0
    finally:
        gates["step"].open.set()
        gates["rearm"].open.set()
    rearming.join(30)
    stepping.join(30)
    assert not rearming.is_alive() and not stepping.is_alive(), "deadlocked: the bus held during the wait"
    status = f.status()
    assert status["state"] == "ready" and status["recoveries"] == 2 and emu.servos[2].reboots == 1
    assert torque(emu) == [1, 1, 1, 1]
    f.bus.close()
