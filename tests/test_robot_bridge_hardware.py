"""The real gripper's raw layer over the emulated bus and a video-file camera."""

import math
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.robot_bridge import xl320
from services.robot_bridge.camera import Camera
from services.robot_bridge.config import GripperConfig, parse
from services.robot_bridge.dynamixel import BusError, ServoBus
from services.robot_bridge.emulator import BusEmulator
from services.robot_bridge.hardware import GripperHardware, valve_servo_goal
from services.robot_bridge.safety import Refused
from shared.gripper.sim import angle_distance, valve_reward
from tests.test_robot_bridge_bus import LATENCY_MS, wait_until

IDS = (1, 2, 3, 4)
VALVE = 5


def config(port: str, settle_s: float = 0.0) -> GripperConfig:
    return parse({
        "bus": {"port": port, "latency_ms": LATENCY_MS},
        "servos": {"ids": list(IDS), "min_step": [200] * 4, "max_step": [820] * 4, "home": [512] * 4,
                   "moving_speed": 1023, "max_step_change": 100, "settle_s": settle_s},
        "valve": {"id": VALVE, "moving_speed": 1023},
        "camera": {"drop_frames": 0},
        "angle": {"source": "servo", "zero_deg": 150.0},
        # A long settle (a step held in flight) needs a step timeout and a watchdog hold beyond it.
        "safety": {"home_tolerance": 3, "reboot_wait_s": 0.0, "step_timeout_s": max(2.0, settle_s + 1.0),
                   "watchdog_hold_s": max(2.0, settle_s + 1.0), "watchdog_off_s": max(10.0, settle_s + 2.0)},
    })


def video(path: Path, frames: int = 200) -> str:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 120))
    for _ in range(frames):
        writer.write(np.full((120, 160, 3), 90, np.uint8))
    writer.release()
    return str(path)


@pytest.fixture
def gripper(tmp_path: Path):
    with BusEmulator(IDS + (VALVE,), positions={1: 400, 2: 600, 3: 512, 4: 512, VALVE: 512}) as emu:
        c = config(emu.port)
        bus = ServoBus(emu.port, 1000000, IDS + (VALVE,), latency_ms=LATENCY_MS)
        hw = GripperHardware(c, "gripper-valve_reset", seed=4, bus=bus,
                             camera=Camera(c.camera, source=video(tmp_path / "cam.avi")))
        try:
            yield emu, hw
        finally:
            hw.close()


def test_reset_homes_turns_the_valve_by_its_servo_and_steps_report(gripper) -> None:
    emu, hw = gripper
    frame, reward, discount, last = hw.reset()
    assert frame.shape == (3, 84, 84) and frame.dtype == np.uint8
    assert (reward, discount, last) == (0.0, 1.0, False)
    assert [emu.snapshot(sid, xl320.PRESENT_POSITION) for sid in IDS] == [512] * 4
    drawn = np.random.RandomState(4).uniform(0, 2 * math.pi)
    raw = (math.degrees(drawn) + 150.0) % 360.0  # zero_deg = 150: angle 0 at the servo's centre
    reachable = valve_servo_goal(raw) * xl320.DEGREES_PER_STEP
    assert abs(emu.snapshot(VALVE, xl320.PRESENT_POSITION) * xl320.DEGREES_PER_STEP - reachable) < 2.0
    assert emu.snapshot(VALVE, xl320.TORQUE_ENABLE) == 0  # let go for the episode
    assert frame[1].max() > 150  # the green target marker is in the image
    frame, reward, discount, last = hw.step(np.array([1.0, -1.0, 0.0, 0.0]))
    info = hw.info()
    assert reward == pytest.approx(valve_reward(hw.valve_angle, hw.target_angle)) and not last
    assert info["clamped"] and info["positions"] and not info["truncated"]
    assert angle_distance(info["valve_angle"], math.radians(reachable - 150.0)) < math.radians(2.0)


def test_a_fault_or_estop_ends_the_episode_truncated(gripper) -> None:
    emu, hw = gripper
    hw.reset()
    emu.overload(2)
    _, _, _, last = hw.step(np.zeros(4))
    assert last and "overload" in hw.info()["reason"]
    assert hw.info()["safety"]["state"] == "ready"  # recovered: the next episode can start
    hw.reset()
    hw.fingers.estop()
    _, _, _, last = hw.step(np.zeros(4))
    assert last and "e-stop" in hw.info()["reason"] and hw.info()["safety"]["state"] == "estop"


def test_a_gripper_waiting_for_its_operator_is_not_re_armed_by_a_reset(gripper) -> None:
    emu, hw = gripper
    hw.reset()
    emu.kill(2)
    _, _, _, last = hw.step(np.zeros(4))  # the recovery cannot reach servo 2
    assert last and hw.info()["safety"]["state"] == "waiting_for_operator"
    emu.kill(2, dead=False)  # the cable comes back by itself; no operator has re-armed
    torque = [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in IDS]
    assert torque[0] == torque[2] == torque[3] == 0  # servo 2 missed the torque-off while cut off
    with pytest.raises(Refused, match="waiting_for_operator"):
        hw.reset()
    assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in IDS] == torque  # nothing armed
    hw.fingers.poll_watchdog()  # it tells the servo that missed the torque-off again
    assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in IDS] == [0] * 4
    hw.fingers.rearm()  # the operator's re-arm
    assert hw.fingers.state.value == "ready"
    hw.reset()


def test_a_valve_turn_that_fails_midway_leaves_the_valve_free_and_an_estop_reaches_it(gripper) -> None:
    emu, hw = gripper
    read = hw.bus.read

    def valve_silent(sid: int, address: int, size: int) -> int:  # its position read fails mid-turn
        if sid == VALVE and address == xl320.PRESENT_POSITION:
            raise BusError(f"servo {sid}: read at {address}: no status packet", [sid])
        return read(sid, address, size)

    hw.bus.read = valve_silent
    with pytest.raises(Refused, match="reset failed"):
        hw.reset()  # scenario 2: the reset turns the valve, torque on, then reads where it is
    hw.bus.read = read
    assert emu.snapshot(VALVE, xl320.TORQUE_ENABLE) == 0
    hw.bus.set_torque(True, [VALVE])  # however it was left on, an e-stop turns it off
    hw.fingers.estop()
    assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in (*IDS, VALVE)] == [0] * 5


def test_the_valve_servo_goal_covers_its_range_and_goes_to_the_nearest_end() -> None:
    assert valve_servo_goal(0.0) == 0 and valve_servo_goal(150.0) == 512
    assert valve_servo_goal(299.9) == 1023 and valve_servo_goal(310.0) == 1023
    assert valve_servo_goal(340.0) == 0


def test_estop_over_zenoh_wins_over_a_hardware_step_in_flight(tmp_path: Path) -> None:

    from nasa.up import free_port
    from services.robot_bridge.client import BridgeEnv
    from services.robot_bridge.server import BridgeServer
    from shared import wire
    from shared.zenoh_session import open_client, open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (
        BusEmulator(IDS + (VALVE,)) as emu,
        open_router(endpoint), open_client(endpoint) as bridge_session, open_client(endpoint) as actor,
    ):
        slow = config(emu.port, settle_s=30.0)
        bus = ServoBus(emu.port, 1000000, IDS + (VALVE,), latency_ms=LATENCY_MS)
        hw = GripperHardware(slow, "gripper-valve", seed=0, bus=bus,
                             camera=Camera(slow.camera, source=video(tmp_path / "cam.avi")))
        server = BridgeServer(bridge_session, "hw", hw, "gripper-valve", log=lambda _: None)
        try:
            with server.serve():
                env = BridgeEnv(actor, "hw", timeout_s=60.0)
                env.reset()
                outcome: list = []
                stepping = threading.Thread(target=lambda: outcome.append(env.step(np.full(4, 0.5))))
                stepping.start()
                wait_until(lambda: emu.snapshot(1, xl320.GOAL_POSITION) != 512)  # the step is in flight
                actor.put(wire.BridgeKeys("hw").estop, wire.encode(wire.BridgeEStop(True, "test")))
                stepping.join(timeout=20)  # long before the step's 30 s settle time
                assert not stepping.is_alive()
                _, reward, _, last = outcome[0]
                assert last and "e-stop" in env.info["reason"] and env.info["safety"]["state"] == "estop"
                assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in IDS] == [0, 0, 0, 0]
        finally:
            hw.close()



def test_an_estop_during_a_rearm_leaves_the_server_and_the_fingers_estopped(gripper) -> None:
    from services.robot_bridge.server import BridgeServer
    from shared import wire

    emu, hw = gripper
    server = BridgeServer(None, "hw", hw, "gripper-valve_reset", log=lambda _: None)  # no Zenoh needed
    server.estop("first")
    set_limits, in_arm, go_on = hw.bus.set_limits, threading.Event(), threading.Event()

    def slow_limits(servo_id: int, moving_speed: int, torque_limit: int) -> None:
        in_arm.set()
        go_on.wait()
        set_limits(servo_id, moving_speed, torque_limit)

    hw.bus.set_limits = slow_limits
    rearming = threading.Thread(target=server.rearm)  # its homing holds the bus
    rearming.start()
    in_arm.wait()
    assert not server.estopped and hw.fingers.status()["state"] == "recovering"
    stopping = threading.Thread(target=server.estop, args=("second",))
    stopping.start()
    wait_until(lambda: hw.fingers.estopped)
    go_on.set()
    rearming.join()
    stopping.join()
    assert server.estopped and hw.fingers.estopped  # one e-stop, not two flags that drift
    assert hw.fingers.status()["state"] == "estop"
    refusal = server.handle_reset(wire.BridgeReset("actor-0", False))
    assert not refusal.ok and "second" in refusal.reason and refusal.info["safety"]["state"] == "estop"
    assert [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in (*IDS, VALVE)] == [0] * 5
