"""The valve-turning gripper in MuJoCo: a stand-in for the real robot, with the suite tasks' raw layer.

`ValveSim` has the interface of `shared.envs.DMCPixels` (reset/step returning
(frame, reward, discount, last), `rng_state`/`set_rng_state`, `action_dim`,
`image_size`), so `FrameStack` and everything above it step it like any suite task.

The four finger servos follow the XL-320: 300 degrees of range in 1024 steps,
a no-load speed of 114 rpm (each actuator's setpoint moves toward its goal at
that speed, as the servo's own speed control does) and its stall torque. An
action in [-1, 1]^4 is the goal of each servo over its range. The episode is
50 control steps; the reward is the valve's shortest angular distance to the
target, divided by pi and negated, so it lies in [-1, 0].

At reset the fingers return home, then in `gripper-valve_reset` the servo under
the valve turns it to a random angle with its own actuator (no teleporting, so
the reset sequence is the hardware's), and a new target is drawn and shown as a
green bar on the ring. In `gripper-valve` the valve stays where the last episode
left it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from shared import gl

gl.configure()  # before mujoco picks a GL backend

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from shared.gripper import ACTION_DIM, TASK_NAMES, frame_shape  # noqa: E402

MODEL_PATH = Path(__file__).with_name("valve.xml")
TASKS: dict[str, Literal["stay", "random"]] = dict(zip(TASK_NAMES, ("stay", "random"), strict=True))
EPISODE_STEPS = 50
CONTROL_PERIOD_S = 0.1

# XL-320 (joint mode): positions 0..1023 over 300 degrees, 512 at the centre; no-load speed 114 rpm.
SERVO_STEPS = 1024
SERVO_CENTRE = 512
SERVO_RAD_PER_STEP = math.radians(300.0) / SERVO_STEPS
SERVO_MAX_SPEED = 114.0 * 2.0 * math.pi / 60.0
VALVE_MAX_TORQUE = 0.39

# Fingers folded away from the handle, so the valve turns freely during a reset.
HOME = np.array([0.0, math.pi / 2, 0.0, math.pi / 2])
HOME_TOLERANCE = math.radians(2.0)
HOME_TIMEOUT_S = 2.0
VALVE_TOLERANCE = math.radians(1.0)
VALVE_TIMEOUT_S = 4.0
VALVE_KP, VALVE_KD = 2.0, 0.04
TARGET_RADIUS = 0.125
# What a checkpoint keeps of the simulation: everything the next physics step reads.
PHYSICS_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


class UnknownGripperTask(ValueError):
    """A task name that is not one of the gripper tasks."""


def wrap_angle(angle: float) -> float:
    """The angle in [0, 2 pi)."""
    return float(angle % (2.0 * math.pi))


def signed_angle(from_angle: float, to_angle: float) -> float:
    """The shortest signed rotation from one angle to another, in [-pi, pi)."""
    return float((to_angle - from_angle + math.pi) % (2.0 * math.pi) - math.pi)


def angle_distance(a: float, b: float) -> float:
    """The shortest angular distance between two angles, in [0, pi]."""
    return abs(signed_angle(a, b))


def valve_reward(valve_angle: float, target_angle: float) -> float:
    """The paper's extrinsic reward: normalised negative distance to the target, in [-1, 0]."""
    return -angle_distance(valve_angle, target_angle) / math.pi


def action_to_goal(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Each action element in [-1, 1] as a goal over its servo's range, on the servo's step grid."""
    a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    goal = low + (a + 1.0) * 0.5 * (high - low)
    return position_to_angle(angle_to_position(goal))


def angle_to_position(angle: np.ndarray) -> np.ndarray:
    """Joint angles (radians, 0 at the centre) as XL-320 goal positions 0..1023."""
    steps = np.rint(np.asarray(angle) / SERVO_RAD_PER_STEP) + SERVO_CENTRE
    return np.clip(steps, 0, SERVO_STEPS - 1).astype(np.int64)


def position_to_angle(position: np.ndarray) -> np.ndarray:
    return (np.asarray(position, dtype=np.float64) - SERVO_CENTRE) * SERVO_RAD_PER_STEP


class ValveSim:
    """The gripper valve task in MuJoCo, rendered to (3, H, W) uint8 frames."""

    def __init__(
        self,
        task: str,
        seed: int,
        image_size: int = 84,
        camera_id: int = 0,
        action_repeat: int = 1,
        render_quality: gl.RenderQuality = "paper",
    ) -> None:
        if task not in TASKS:
            raise UnknownGripperTask(f"unknown gripper task {task!r}; valid: {', '.join(TASKS)}")
        if action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        self.task = task
        self.scenario = TASKS[task]
        self.model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
        gl.apply_render_quality(self.model, render_quality)
        if not 0 <= camera_id < self.model.ncam:
            raise ValueError(f"camera_id {camera_id} out of range: the model has {self.model.ncam} camera(s)")
        self.data = mujoco.MjData(self.model)
        self.action_dim = ACTION_DIM
        self.image_size = image_size
        self.frame_shape = frame_shape(image_size)
        self.camera_id = camera_id
        self.action_repeat = action_repeat
        self._random = np.random.RandomState(seed)
        self._renderer: mujoco.Renderer | None = None
        self._low = self.model.actuator_ctrlrange[:4, 0].copy()
        self._high = self.model.actuator_ctrlrange[:4, 1].copy()
        fingers = ("a0", "a1", "b0", "b1")
        self._finger_qpos = np.array([self.model.jnt_qposadr[self.model.joint(n).id] for n in fingers])
        valve = self.model.joint("valve")
        self._valve_qpos = int(self.model.jnt_qposadr[valve.id])
        self._valve_dof = int(self.model.jnt_dofadr[valve.id])
        self._target_mocap = int(self.model.body("target").mocapid[0])
        self._substeps = max(1, round(CONTROL_PERIOD_S / self.model.opt.timestep))
        self._max_delta = SERVO_MAX_SPEED * self.model.opt.timestep
        # The power-on state: fingers at home (held there), valve at 0, target at 0.
        self.data.qpos[self._finger_qpos] = HOME
        self._setpoint = HOME.copy()
        self.data.ctrl[:4] = HOME
        self.target_angle = 0.0
        self._place_target(0.0)
        self._steps = 0
        self._last = True
        mujoco.mj_forward(self.model, self.data)

    # -- state the bridge reports ------------------------------------------------------------
    @property
    def valve_angle(self) -> float:
        return wrap_angle(self.data.qpos[self._valve_qpos])

    def servo_positions(self) -> np.ndarray:
        """The finger servos' present positions as XL-320 steps."""
        return angle_to_position(self.data.qpos[self._finger_qpos])

    def reward(self) -> float:
        return valve_reward(self.valve_angle, self.target_angle)

    # -- raw layer -----------------------------------------------------------------------------
    def render(self) -> np.ndarray:
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
        self._renderer.update_scene(self.data, camera=self.camera_id)
        return np.ascontiguousarray(self._renderer.render().transpose(2, 0, 1))

    def rng_state(self) -> dict:
        """The random state that draws targets (and reset angles), and the whole physical state.

        Scenario 1 carries the valve, and the fingers' pose, from one episode into the next, so
        a run resumed from this state takes the same path as one never stopped only if the
        physics comes back bit for bit: MuJoCo's integration state (positions, velocities,
        controls, the solver's warm start, the target's mocap pose) and the servo setpoints.
        `valve_angle` is kept beside it for states that say only where the valve stands."""
        name, keys, pos, has_gauss, cached = self._random.get_state()
        physics = np.empty(mujoco.mj_stateSize(self.model, PHYSICS_STATE))
        mujoco.mj_getState(self.model, self.data, physics, PHYSICS_STATE)
        return {
            "name": name, "keys": keys.tolist(), "pos": pos, "has_gauss": has_gauss, "cached": cached,
            "valve_angle": self.valve_angle,
            "physics": physics.tolist(), "setpoint": self._setpoint.tolist(),
            "target_angle": self.target_angle,
        }

    def set_rng_state(self, state: dict) -> None:
        """Restore a state from `rng_state`. A state that does not fit this model raises
        ValueError before anything is changed."""
        keys = np.asarray(state["keys"], dtype=np.uint32)
        physics = state.get("physics")
        if physics is not None:
            checked = self._check_physics(physics, state["setpoint"], state["target_angle"])
        self._random.set_state((state["name"], keys, state["pos"], state["has_gauss"], state["cached"]))
        if physics is not None:
            self._set_physics(*checked)
            return
        # A state with only the valve's angle: put the valve back there, since scenario 1 starts
        # each episode from it; the fingers go home first, as at a reset, so the valve is not put
        # into one. Close to the stopped run's state, not bit for bit.
        self._go_home()
        self.data.qpos[self._valve_qpos] = float(state["valve_angle"])
        self.data.qvel[self._valve_dof] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        self._go_home()
        if self.scenario == "random":
            self._turn_valve_to(self._random.uniform(0.0, 2.0 * math.pi))
        self.target_angle = float(self._random.uniform(0.0, 2.0 * math.pi))
        self._place_target(self.target_angle)
        mujoco.mj_forward(self.model, self.data)
        self._steps = 0
        self._last = False
        return self.render(), 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action shape {action.shape}, expected ({self.action_dim},)")
        if not np.all(np.isfinite(action)):
            from shared.envs import EnvFault  # shared.envs loads this module on demand

            raise EnvFault(f"action has non-finite values: {action}")
        if self._last:
            raise RuntimeError("step() after the episode ended: call reset() first")
        goal = action_to_goal(action, self._low, self._high)
        reward = 0.0
        for _ in range(self.action_repeat):
            for _ in range(self._substeps):
                self._servo_substep(goal)
            reward += self.reward()
            self._steps += 1
            if self._steps >= EPISODE_STEPS:
                self._last = True
                break
        # A time limit, never a terminal: the discount stays 1 as in the suite tasks.
        return self.render(), reward, 1.0, self._last

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _check_physics(
        self, physics: list[float], setpoint: list[float], target_angle: float
    ) -> tuple[np.ndarray, np.ndarray, float]:
        values = np.asarray(physics, dtype=np.float64)
        size = mujoco.mj_stateSize(self.model, PHYSICS_STATE)
        if values.shape != (size,):
            raise ValueError(f"the gripper's physics state has {values.size} values, this model needs {size}")
        goal = np.asarray(setpoint, dtype=np.float64)
        if goal.shape != self._setpoint.shape:
            raise ValueError(
                f"the gripper's servo setpoints have shape {goal.shape}, expected {self._setpoint.shape}"
            )
        target = float(target_angle)
        if not (np.all(np.isfinite(values)) and np.all(np.isfinite(goal)) and math.isfinite(target)):
            raise ValueError("the gripper's physics state holds values that are not finite")
        return values, goal.copy(), target

    def _set_physics(self, physics: np.ndarray, setpoint: np.ndarray, target_angle: float) -> None:
        mujoco.mj_setState(self.model, self.data, physics, PHYSICS_STATE)
        self._setpoint = setpoint
        self.target_angle = target_angle
        mujoco.mj_forward(self.model, self.data)

    # -- mechanics -----------------------------------------------------------------------------
    def _servo_substep(self, goal: np.ndarray) -> None:
        """One physics step with each finger setpoint moved toward its goal at the servo's speed."""
        self._setpoint += np.clip(goal - self._setpoint, -self._max_delta, self._max_delta)
        self.data.ctrl[:4] = self._setpoint
        mujoco.mj_step(self.model, self.data)

    def _go_home(self) -> None:
        for _ in range(round(HOME_TIMEOUT_S / self.model.opt.timestep)):
            self._servo_substep(HOME)
            if np.all(np.abs(self.data.qpos[self._finger_qpos] - HOME) < HOME_TOLERANCE):
                break

    def _turn_valve_to(self, angle: float) -> None:
        """The valve servo turns the valve the short way round, then lets go (torque off)."""
        for _ in range(round(VALVE_TIMEOUT_S / self.model.opt.timestep)):
            error = signed_angle(self.valve_angle, angle)
            velocity = self.data.qvel[self._valve_dof]
            if abs(error) < VALVE_TOLERANCE and abs(velocity) < 0.05:
                break
            torque = VALVE_KP * error - VALVE_KD * velocity
            self.data.ctrl[4] = np.clip(torque, -VALVE_MAX_TORQUE, VALVE_MAX_TORQUE)
            self._servo_substep(HOME)
        self.data.ctrl[4] = 0.0

    def _place_target(self, angle: float) -> None:
        x, y = TARGET_RADIUS * math.cos(angle), TARGET_RADIUS * math.sin(angle)
        self.data.mocap_pos[self._target_mocap, :2] = x, y
        self.data.mocap_quat[self._target_mocap] = math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)
