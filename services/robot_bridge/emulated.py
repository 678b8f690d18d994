"""The real gripper's code path without the gripper: `GripperHardware` on an emulated bus.

`EmulatedGripper` runs the Dynamixel Protocol 2.0 emulator (`emulator.BusEmulator`, on a pty) in
the bridge's own process, and drives it through the real driver (`dynamixel-sdk`) and every
interlock, exactly as it would drive the servos. Its camera (`DrawnCamera`) draws what the
emulated servos do: the valve's marker at the valve servo's angle and one line per finger servo
at its position, so frames follow the actions. Nothing here pushes the valve: the fingers do not
touch it, so this checks the hardware path (bus, safety, frames, rewards over Zenoh), not learning.
"""

from __future__ import annotations

import math

import numpy as np

from services.robot_bridge import xl320
from services.robot_bridge.config import GripperConfig, parse
from services.robot_bridge.emulator import BusEmulator
from services.robot_bridge.hardware import GripperHardware

FINGER_IDS = (1, 2, 3, 4)
VALVE_ID = 5
# The USB adapter's latency timer, generous: the emulator answers from a thread of a process
# that may share a busy CPU, and a late answer would read as a dead servo.
LATENCY_MS = 200.0


def emulated_config(port: str, image_size: int = 84) -> GripperConfig:
    """A gripper config for the emulated bus: the example's layout, a small camera, the valve
    angle read from the valve servo (no marker to see)."""
    return parse({
        "bus": {"port": port, "latency_ms": LATENCY_MS},
        "servos": {"ids": list(FINGER_IDS), "min_step": [200] * 4, "max_step": [820] * 4,
                   "home": [512, 820, 512, 820], "moving_speed": 1023, "max_step_change": 150,
                   "settle_s": 0.02},
        "valve": {"id": VALVE_ID, "moving_speed": 1023},
        "camera": {"width": 160, "height": 120, "image_size": image_size, "drop_frames": 0},
        "angle": {"source": "servo", "zero_deg": 150.0},
        # No guard: the emulated servos live in this process and die with it.
        "safety": {"home_tolerance": 3, "reboot_wait_s": 0.0, "torque_guard": False},
    }, source="<emulated gripper>")


class DrawnCamera:
    """A camera for the emulated bus: BGR frames drawn from the emulated servos' positions."""

    def __init__(self, emulator: BusEmulator, config: GripperConfig) -> None:
        self.emulator = emulator
        self.config = config.camera
        self.valve_id = config.valve.id
        self.finger_ids = tuple(config.servos.ids)

    def frame(self) -> np.ndarray:
        import cv2

        h, w = self.config.height, self.config.width
        image = np.full((h, w, 3), 90, np.uint8)
        cx, cy = round(self.config.valve_centre[0] * w), round(self.config.valve_centre[1] * h)
        valve = self.emulator.snapshot(self.valve_id, xl320.PRESENT_POSITION)
        raw = math.radians(valve * xl320.DEGREES_PER_STEP)
        r = 0.3 * h
        cv2.line(image, (cx, cy), (round(cx + r * math.cos(raw)), round(cy - r * math.sin(raw))),
                 (40, 40, 220), thickness=3)  # the valve's red angle marker, BGR
        for i, sid in enumerate(self.finger_ids):
            x = round((i + 0.5) * w / len(self.finger_ids))
            turn = math.radians(self.emulator.snapshot(sid, xl320.PRESENT_POSITION) * xl320.DEGREES_PER_STEP)
            tip = (round(x + 0.12 * h * math.cos(turn)), round(h - 6 - 0.12 * h * math.sin(turn)))
            cv2.line(image, (x, h - 6), tip, (220, 160, 40), thickness=2)
        return image

    def close(self) -> None:
        pass


class EmulatedGripper(GripperHardware):
    """`GripperHardware` over a `BusEmulator` it owns (closed with it) and a `DrawnCamera`."""

    def __init__(self, task: str, seed: int, image_size: int = 84) -> None:
        self.emulator = BusEmulator(FINGER_IDS + (VALVE_ID,)).__enter__()
        try:
            config = emulated_config(self.emulator.port, image_size)
            super().__init__(config, task, seed, camera=DrawnCamera(self.emulator, config))
        except BaseException:
            self.emulator.close()
            raise

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.emulator.close()
