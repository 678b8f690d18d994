"""The torque guard: a real bridge process on the emulated bus's pty, killed or stopped by real signals."""

import os
import re
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from bench.processes import processes_with, stop_group
from services.robot_bridge import xl320
from services.robot_bridge.client import BridgeEnv
from services.robot_bridge.dynamixel import ServoBus
from services.robot_bridge.emulator import BusEmulator
from services.robot_bridge.guard import TorqueGuard
from shared import wire
from shared.zenoh_session import token_up
from tests.test_robot_bridge_bus import LATENCY_MS
from tests.test_robot_bridge_hardware import video
from tests.test_robot_bridge_zenoh import endpoint, sessions, wait_until  # noqa: F401 (fixtures)

IDS = (1, 2, 3, 4)
VALVE = 5
ALL = IDS + (VALVE,)
# The bridge's main, as run by `python -m services.robot_bridge`, with a video file for the webcam
# this machine does not have; the bus is the emulator's pty, named in the config.
BRIDGE = (
    "import functools, sys\n"
    "from services.robot_bridge import hardware, main\n"
    "hardware.Camera = functools.partial(hardware.Camera, source=sys.argv[1])\n"
    "main.main(sys.argv[2:])\n"
)
CONFIG = """
[bus]
port = "{port}"
latency_ms = {latency_ms}
[servos]
ids = [1, 2, 3, 4]
min_step = [200, 200, 200, 200]
max_step = [820, 820, 820, 820]
home = [512, 512, 512, 512]
moving_speed = 1023
settle_s = 0.0
[valve]
id = 5
[camera]
drop_frames = 0
[angle]
source = "servo"
[safety]
home_tolerance = 3
reboot_wait_s = 0.0
"""


def torque(emu: BusEmulator, ids: tuple[int, ...] = ALL) -> list[int]:
    return [emu.snapshot(sid, xl320.TORQUE_ENABLE) for sid in ids]


def gone(pid: int) -> bool:
    """Exited (a zombie counts: it holds no port and writes nothing)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


MARK = "BRIDGE_TEST_MARK"
"""In the environment of a fixture's bridge, and so of its guard, whatever session that runs in."""


def left_running(mark: str, deadline_s: float = 60.0) -> list[tuple[int, list[str]]]:
    """The processes carrying `mark` once they have had `deadline_s` to exit (a killed bridge's guard
    turns torque off, then exits; a stood-down one exits at once), SIGKILLed then, so none outlives
    its test: a guard retrying the port by name would write to the next test's pty of that name."""
    end = time.monotonic() + deadline_s
    while (left := processes_with(MARK, mark)) and time.monotonic() < end:
        time.sleep(0.1)
    for pid, _ in left:
        os.kill(pid, signal.SIGKILL)
    return left


@pytest.fixture
def bridge(sessions, endpoint: str, tmp_path: Path) -> Iterator[tuple]:  # noqa: F811 (fixtures)
    """A bridge process serving the emulated servos, torque taken by a reset over Zenoh; its log.
    A bridge still running after the test is stopped as an operator would (SIGTERM: it turns torque
    off and stands its guard down; SIGKILL only if it does not exit in time), and neither it nor a
    guard may be left once the emulator closes."""
    _, actor = sessions
    mark = uuid.uuid4().hex
    with BusEmulator(ALL) as emu:
        config = tmp_path / "gripper.toml"
        config.write_text(CONFIG.format(port=emu.port, latency_ms=LATENCY_MS))
        log = tmp_path / "bridge.log"
        argv = ["--bridge-id", "g1", "--task", "gripper-valve", "--config", str(config),
                "--connect", endpoint]
        with log.open("w") as err:
            proc = subprocess.Popen([sys.executable, "-c", BRIDGE, video(tmp_path / "cam.avi"), *argv],
                                    stderr=err, env={**os.environ, MARK: mark}, start_new_session=True)
        try:
            wait_until(lambda: token_up(actor, wire.BridgeKeys("g1").alive), deadline_s=120.0)
            env = BridgeEnv(actor, "g1", timeout_s=60.0)
            env.reset()
            env.step(np.zeros(4, np.float32))
            assert torque(emu, IDS) == [1, 1, 1, 1]
            yield emu, proc, log
        finally:
            stop_group(proc, ((signal.SIGTERM, 60.0),))
            left = left_running(mark)  # while the emulator still holds the port
        assert left == [], f"left running after the test: {left}\n{log.read_text()}"


def guard_pid(log: Path) -> int:
    found = re.search(r"torque guard running \(pid (\d+)\)", log.read_text())
    assert found, log.read_text()
    return int(found.group(1))


def test_a_killed_bridge_leaves_its_guard_to_turn_torque_off_on_every_servo(bridge) -> None:
    emu, proc, log = bridge
    pid = guard_pid(log)
    assert os.getsid(pid) == pid  # its own session: a Ctrl-C to the bridge's process group misses it
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    wait_until(lambda: torque(emu) == [0] * len(ALL), deadline_s=60.0)
    wait_until(lambda: gone(pid), deadline_s=60.0)
    assert f"the bridge died: turned torque off on servos {list(ALL)} at {emu.port}" in log.read_text()


def test_a_clean_stop_turns_torque_off_and_stands_the_guard_down(bridge) -> None:
    emu, proc, log = bridge
    pid = guard_pid(log)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    assert torque(emu) == [0] * len(ALL)  # the bridge's own torque-off
    wait_until(lambda: gone(pid), deadline_s=60.0)
    text = log.read_text()
    assert "e-stop: SIGTERM" in text and "[torque guard]" not in text, text


def test_a_second_bridge_on_the_same_port_is_refused_and_the_first_runs_on(
    bridge, sessions, endpoint: str, tmp_path: Path  # noqa: F811 (fixtures)
) -> None:
    """A bridge launched twice by mistake, under another id (its Zenoh claim would not stop it):
    it exits 1 with one line naming the port and the bridge holding it, and the first steps on."""
    emu, proc, _ = bridge
    argv = ["--bridge-id", "g2", "--task", "gripper-valve", "--config", str(tmp_path / "gripper.toml"),
            "--connect", endpoint]
    second = subprocess.run([sys.executable, "-c", BRIDGE, video(tmp_path / "cam2.avi"), *argv],
                            capture_output=True, text=True, timeout=120)
    assert second.returncode == 1, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"robot_bridge: error: cannot open {emu.port}: in use by another"), lines
    assert f"pid {proc.pid}: " in lines[0], lines[0]
    assert proc.poll() is None
    env = BridgeEnv(sessions[1], "g1", timeout_s=60.0)
    env.reset()
    env.step(np.zeros(4, np.float32))
    assert env.fault() == "ok" and torque(emu, IDS) == [1, 1, 1, 1]


def test_a_calibration_on_a_port_a_bridge_holds_is_refused_in_one_line(tmp_path: Path) -> None:
    with BusEmulator(ALL) as emu:
        config = tmp_path / "gripper.toml"
        config.write_text(CONFIG.format(port=emu.port, latency_ms=LATENCY_MS))
        bus = ServoBus(emu.port, 1000000, ALL, latency_ms=LATENCY_MS)  # the bridge's
        try:
            seen = emu.packets_seen
            done = subprocess.run([sys.executable, "-m", "services.robot_bridge.operate", "calibrate",
                                   "--config", str(config), "--samples", "1"],
                                  capture_output=True, text=True, timeout=120)
            assert done.returncode == 1, done.stderr
            lines = done.stderr.strip().splitlines()
            assert len(lines) == 1, lines
            assert lines[0].startswith(f"calibrate: error: cannot open {emu.port}: in use"), lines
            assert f"pid {os.getpid()}: " in lines[0] and emu.packets_seen == seen
        finally:
            bus.close()


def test_a_calibration_without_its_adapter_is_one_line_and_exit_1(tmp_path: Path) -> None:
    config = tmp_path / "gripper.toml"
    missing = tmp_path / "ttyUSB9"
    config.write_text(CONFIG.format(port=missing, latency_ms=LATENCY_MS))
    done = subprocess.run([sys.executable, "-m", "services.robot_bridge.operate", "calibrate",
                           "--config", str(config), "--samples", "1"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"calibrate: error: cannot open {missing}: "), lines


def test_a_guard_ignores_sigterm_and_stood_down_exits_without_writing(tmp_path: Path) -> None:
    with BusEmulator(IDS) as emu:
        bus = ServoBus(emu.port, 1000000, IDS, latency_ms=LATENCY_MS)
        bus.set_torque(True)
        bus.close()
        guard = TorqueGuard(emu.port, 1000000, IDS, LATENCY_MS)
        seen = emu.packets_seen
        guard.process.send_signal(signal.SIGTERM)  # a stop meant for the bridge's group: ignored
        guard.close(stand_down=True)
        assert guard.process.wait(timeout=60) == 0
        assert emu.packets_seen == seen and torque(emu, IDS) == [1, 1, 1, 1]  # left to the bridge


def test_a_guard_that_cannot_open_the_port_gives_up_after_its_tries_with_one_line(tmp_path: Path) -> None:
    read_end, write_end = os.pipe()
    missing = str(tmp_path / "ttyUSB9")
    argv = [sys.executable, "-m", "services.robot_bridge.guard", "--fd", str(read_end), "--port", missing,
            "--baud", "1000000", "--latency-ms", "16", "--ids", "1,2"]
    proc = subprocess.Popen(argv, pass_fds=(read_end,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    os.close(read_end)
    os.close(write_end)  # EOF without the stand-down word: as if the bridge had died
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert f"could not turn torque off on servos [1, 2] at {missing} after 5 tries" in lines[0]
    assert "cannot open" in lines[0] and "cut the servos' power" in lines[0]


def test_a_port_that_cannot_be_opened_is_one_line_and_exit_1(tmp_path: Path) -> None:
    config = tmp_path / "gripper.toml"
    config.write_text(CONFIG.format(port=tmp_path / "ttyUSB9", latency_ms=LATENCY_MS))
    argv = ["--bridge-id", "g1", "--task", "gripper-valve", "--config", str(config)]
    proc = subprocess.run([sys.executable, "-c", BRIDGE, str(tmp_path / "cam.avi"), *argv],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("robot_bridge: error: "), proc.stderr
    assert "ttyUSB9" in lines[0]


def test_a_failed_start_closes_what_it_opened_and_stands_the_guard_down(tmp_path: Path, monkeypatch) -> None:
    """The ArUco angle, built after the guard, fails: the bus and the camera are closed (the next try
    must take them) and the guard stands down, instead of reporting a dead bridge and writing."""
    from services.robot_bridge import config as config_module
    from services.robot_bridge import hardware
    from services.robot_bridge.camera import CameraUnavailable

    closed: list[str] = []
    guards: list[TorqueGuard] = []

    def spy(name: str, cls: type, **fixed) -> type:
        class Spied(cls):
            def __init__(self, *args, **kwargs) -> None:
                super().__init__(*args, **kwargs, **fixed)
                guards.extend([self] if name == "guard" else [])

            def close(self, *args, **kwargs) -> None:
                closed.append(name)
                super().close(*args, **kwargs)
        return Spied

    def no_aruco(*args, **kwargs):
        raise CameraUnavailable("this OpenCV has no ArUco module")

    monkeypatch.setattr(hardware, "ServoBus", spy("bus", ServoBus))
    monkeypatch.setattr(hardware, "Camera", spy("camera", hardware.Camera, source=video(tmp_path / "c.avi")))
    monkeypatch.setattr(hardware, "TorqueGuard", spy("guard", TorqueGuard))
    monkeypatch.setattr(hardware, "ArucoAngle", no_aruco)
    with BusEmulator(ALL) as emu:
        path = tmp_path / "gripper.toml"
        path.write_text(CONFIG.format(port=emu.port, latency_ms=LATENCY_MS).replace('"servo"', '"aruco"'))
        with pytest.raises(CameraUnavailable):
            hardware.GripperHardware(config_module.load(path), "gripper-valve", 0)
        seen = emu.packets_seen
        assert len(guards) == 1
        assert guards[0].process.wait(timeout=60) == 0
        assert emu.packets_seen == seen  # stood down: it wrote nothing
        assert sorted(closed) == ["bus", "camera", "guard"]
