"""The real gripper as a raw environment layer, with the stand-in's interface (`ValveSim`).

`GripperHardware` steps the finger servos through `SafeFingers`, takes each frame from the
camera after the action, measures the valve angle (ArUco marker or valve servo) and computes
the same reward as the stand-in. The target angle, drawn per episode, is drawn onto the camera
frame around the valve centre, since the policy sees only pixels. In `gripper-valve_reset` the
servo under the valve turns it to a random angle at reset, then lets go (torque off). An
XL-320 reaches 300 of the 360 degrees: a drawn angle in the other 60 goes to the nearest end.

A step the interlocks refuse or cut short (e-stop, fault, watchdog, timeout) ends the episode
truncated, with the reason in `info()`; it never raises to the client.
"""

from __future__ import annotations

import math
import time

import numpy as np

from services.robot_bridge import xl320
from services.robot_bridge.camera import ArucoAngle, Camera, servo_angle, to_observation
from services.robot_bridge.config import GripperConfig
from services.robot_bridge.dynamixel import BusError, ServoBus
from services.robot_bridge.guard import TorqueGuard
from services.robot_bridge.safety import Refused, SafeFingers
from shared.gripper.sim import EPISODE_STEPS, TASKS, UnknownGripperTask, valve_reward

VALVE_TOLERANCE_STEPS = 5
VALVE_TURN_TIMEOUT_S = 10.0


def valve_servo_goal(raw_degrees: float) -> int:
    """The valve servo's goal for a raw angle in [0, 360): its 300-degree range, else the nearest end."""
    span = (xl320.POSITION_MAX + 1) * xl320.DEGREES_PER_STEP
    if raw_degrees >= span:
        return xl320.POSITION_MAX if raw_degrees < (span + 360.0) / 2 else 0
    return min(round(raw_degrees / xl320.DEGREES_PER_STEP), xl320.POSITION_MAX)


class GripperHardware:
    """reset()/step() -> (frame (3, H, W) uint8, reward, discount, last), like `ValveSim`."""

    def __init__(
        self, config: GripperConfig, task: str, seed: int,
        bus: ServoBus | None = None, camera: Camera | None = None,
    ) -> None:
        if task not in TASKS:
            raise UnknownGripperTask(f"unknown gripper task {task!r}; valid: {', '.join(TASKS)}")
        self.config = config
        self.scenario = TASKS[task]
        if self.scenario == "random" and config.valve.id == 0:
            raise ValueError(f"{task} turns the valve at reset: the config needs a valve servo (valve.id)")
        ids = tuple(config.servos.ids) + ((config.valve.id,) if config.valve.id else ())
        self.bus = bus or ServoBus(config.bus.port, config.bus.baud, ids, config.bus.latency_ms)
        self.camera = camera
        self.guard: TorqueGuard | None = None
        try:
            self.fingers = SafeFingers(self.bus, config.servos, config.safety)
            if self.camera is None:
                self.camera = Camera(config.camera)
            # Started before any torque goes on. A bus handed in is its owner's (tests): no guard.
            if bus is None and config.safety.torque_guard:
                self.guard = TorqueGuard(config.bus.port, config.bus.baud, ids, config.bus.latency_ms)
            self._aruco = ArucoAngle(config.angle) if config.angle.source == "aruco" else None
        except BaseException:
            # What this opened is closed, so the next try can take the port and the camera; no
            # torque is on yet, so the guard stands down. A bus or camera handed in is its owner's.
            if self.guard is not None:
                self.guard.close(stand_down=True)
            if camera is None and self.camera is not None:
                self.camera.close()
            if bus is None:
                self.bus.close()
            raise
        self._random = np.random.RandomState(seed)
        self.action_dim = 4
        self.image_size = config.camera.image_size
        self.frame_shape = (3, self.image_size, self.image_size)
        self.valve_angle = 0.0
        self.target_angle = 0.0
        self.angle_seen = False
        self._steps = 0
        self._info: dict = {}

    def rng_state(self) -> dict:
        name, keys, pos, has_gauss, cached = self._random.get_state()
        return {"name": name, "keys": keys.tolist(), "pos": pos, "has_gauss": has_gauss, "cached": cached}

    def set_rng_state(self, state: dict) -> None:
        keys = np.asarray(state["keys"], dtype=np.uint32)
        self._random.set_state((state["name"], keys, state["pos"], state["has_gauss"], state["cached"]))

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        """Home the fingers, turn the valve (scenario 2), draw a target; raises Refused if it cannot."""
        try:
            self.fingers.arm()
            if not self.fingers.go_home():
                raise Refused(f"the fingers did not reach home within {self.config.safety.home_timeout_s} s")
            if self.scenario == "random":
                self._turn_valve(self._random.uniform(0.0, 2.0 * math.pi))
        except BusError as e:
            raise Refused(f"reset failed: {e}") from e
        self.target_angle = float(self._random.uniform(0.0, 2.0 * math.pi))
        self._steps = 0
        frame = self._observe()
        self._info = self._report(None, "")
        return frame, 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        reason, report = "", None
        try:
            report = self.fingers.step(action, settle_s=self.config.servos.settle_s)
            reason = report.reason
        except Refused as e:
            reason = str(e)
            self.fingers.wait_torque_cut()
        frame = self._observe()
        self._steps += 1
        truncated = bool(reason)
        self._info = self._report(report, reason)
        last = truncated or self._steps >= EPISODE_STEPS
        return frame, valve_reward(self.valve_angle, self.target_angle), 1.0, last

    def info(self) -> dict:
        """The last reset's or step's measurements and safety state (the bridge's info map)."""
        return dict(self._info)

    def close(self) -> None:
        """Close the camera and the bus; with a guard, torque off first, then the guard stands
        down, unless a servo missed the torque-off: the guard then tries too, once the bus is closed."""
        reached = self.guard is None or not self.fingers.estop()
        try:
            self.camera.close()
            self.bus.close()
        finally:
            if self.guard is not None:
                self.guard.close(stand_down=reached)

    # -- internals -----------------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        bgr = self.camera.frame()
        angle = self._measure(bgr)
        self.angle_seen = angle is not None
        if angle is not None:
            self.valve_angle = angle  # an unseen marker keeps the last angle (reported in info)
        return to_observation(self._draw_target(bgr), self.image_size)

    def _measure(self, bgr: np.ndarray) -> float | None:
        if self._aruco is not None:
            return self._aruco.angle(bgr)
        try:
            with self.fingers.bus_lock:
                position = self.bus.read(self.config.valve.id, xl320.PRESENT_POSITION, 2)
            return servo_angle(position, self.config.angle)
        except BusError:
            return None

    def _image_degrees(self, angle: float) -> float:
        """A valve angle as the raw reading (degrees) it corresponds to: calibration inverted."""
        a = self.config.angle
        return (a.zero_deg + a.direction * math.degrees(angle)) % 360.0

    def _draw_target(self, bgr: np.ndarray) -> np.ndarray:
        import cv2

        out = bgr.copy()
        h, w = out.shape[:2]
        cx, cy = self.config.camera.valve_centre[0] * w, self.config.camera.valve_centre[1] * h
        theta = math.radians(self._image_degrees(self.target_angle))
        r = self.config.camera.target_radius * h
        tip = (round(cx + r * math.cos(theta)), round(cy - r * math.sin(theta)))
        cv2.circle(out, tip, max(3, h // 40), (40, 220, 40), thickness=-1)  # green, BGR
        return out

    def _turn_valve(self, angle: float) -> None:
        """The valve servo turns the valve to `angle` (nearest reachable), then torque off."""
        vid, v = self.config.valve.id, self.config.valve
        goal = valve_servo_goal(self._image_degrees(angle))
        lock = self.fingers.bus_lock
        try:
            with lock:
                self.bus.set_limits(vid, v.moving_speed, v.torque_limit)
                self.bus.set_torque(True, [vid])
                self.bus.write(vid, xl320.GOAL_POSITION, goal, 2)
            end = time.monotonic() + VALVE_TURN_TIMEOUT_S
            while True:
                with lock:
                    present = self.bus.read(vid, xl320.PRESENT_POSITION, 2)
                arrived = abs(present - goal) <= VALVE_TOLERANCE_STEPS
                if arrived or time.monotonic() > end or self.fingers.estopped:
                    break
                self.fingers.touch()  # the fingers hold home meanwhile: the watchdog must not fire
                time.sleep(0.02)
        finally:
            with lock:  # free, so the fingers can turn it; also when the turn failed midway
                self.bus.set_torque(False, [vid])

    def _report(self, report, reason: str) -> dict:
        state = report.state if report is not None else None
        return {
            "valve_angle": self.valve_angle,
            "target_angle": self.target_angle,
            "angle_seen": self.angle_seen,
            "positions": state.position.tolist() if state is not None else [],
            "loads": state.load.tolist() if state is not None else [],
            "error_bits": state.error.tolist() if state is not None else [],
            "clamped": bool(report.clamped) if report is not None else False,
            "step_latency_s": float(report.latency_s) if report is not None else 0.0,
            "truncated": bool(reason),
            "reason": reason,
            "safety": self.fingers.status(),
        }
