"""The MuJoCo stand-in of the gripper valve task: reward, both reset scenarios, determinism, frames."""

import math

import numpy as np
import pytest

from shared.gripper import sim
from shared.gripper.sim import ValveSim, angle_distance, valve_reward


def test_reward_wraps_around() -> None:
    assert valve_reward(math.radians(359), math.radians(1)) == pytest.approx(-2.0 / 180.0)
    assert valve_reward(math.radians(1), math.radians(359)) == pytest.approx(-2.0 / 180.0)
    assert valve_reward(0.0, math.pi) == pytest.approx(-1.0)
    assert valve_reward(2.0, 2.0 + 4 * math.pi) == pytest.approx(0.0, abs=1e-12)
    angles = np.random.default_rng(0).uniform(-10, 10, size=(200, 2))
    distances = [angle_distance(a, b) for a, b in angles]
    assert 0.0 <= min(distances) and max(distances) <= math.pi


def test_actions_map_to_the_servo_step_grid() -> None:
    low, high = np.full(4, -math.radians(150)), np.full(4, math.radians(150))
    goal = sim.action_to_goal(np.array([-1.0, 1.0, 0.0, 5.0]), low, high)
    assert list(sim.angle_to_position(goal)) == [0, 1023, 512, 1023]
    steps = goal / sim.SERVO_RAD_PER_STEP
    assert np.allclose(steps, np.rint(steps))


class Recording(ValveSim):
    """Records the valve angle after every physics step, to show how a reset moves it."""

    def __init__(self, *args, **kwargs) -> None:
        self.trace: list[float] = []
        super().__init__(*args, **kwargs)

    def _servo_substep(self, goal: np.ndarray) -> None:
        super()._servo_substep(goal)
        self.trace.append(float(self.data.qpos[self._valve_qpos]))


def test_reset_scenario_turns_the_valve_with_its_own_actuator() -> None:
    env = Recording("gripper-valve_reset", seed=3, render_quality="fast")
    draws = np.random.RandomState(3)
    try:
        for _ in range(3):
            env.trace.clear()
            env.reset()
            expected_valve, expected_target = draws.uniform(0, 2 * math.pi), draws.uniform(0, 2 * math.pi)
            assert angle_distance(env.valve_angle, expected_valve) < math.radians(2.0)
            assert env.target_angle == pytest.approx(expected_target)
            assert env.data.ctrl[4] == 0.0  # torque off for the episode
            # No teleport: the valve travelled in physics steps no bigger than its speed allows.
            jumps = np.abs(np.diff(env.trace))
            assert len(env.trace) > 1 and jumps.max() < 100.0 * env.model.opt.timestep
    finally:
        env.close()


def test_stay_scenario_leaves_the_valve_where_it_is() -> None:
    env = ValveSim("gripper-valve", seed=5, render_quality="fast")
    try:
        env.reset()
        env._turn_valve_to(math.radians(100))  # as if the fingers had turned it there
        before = env.valve_angle
        env.reset()
        assert angle_distance(env.valve_angle, before) < math.radians(0.5)
        assert env.data.ctrl[4] == 0.0
        targets = []
        for _ in range(4):
            env.reset()
            targets.append(env.target_angle)
        assert len(set(targets)) == 4  # a new target every episode
    finally:
        env.close()


def _episode(env: ValveSim, seed: int) -> tuple[list[np.ndarray], list[float]]:
    actions = np.random.default_rng(seed).uniform(-1, 1, size=(sim.EPISODE_STEPS, 4))
    frame, _, _, _ = env.reset()
    frames, rewards = [frame], []
    for i, action in enumerate(actions):
        frame, reward, discount, last = env.step(action)
        frames.append(frame)
        rewards.append(reward)
        assert discount == 1.0
        assert last == (i == sim.EPISODE_STEPS - 1)
    return frames, rewards


def _angle_only(state: dict) -> dict:
    """A state that says only where the valve stands (the draws and the angle, no physics)."""
    return {k: v for k, v in state.items() if k not in ("physics", "setpoint", "target_angle")}


def test_deterministic_under_a_seed() -> None:
    a = ValveSim("gripper-valve_reset", seed=11, render_quality="fast")
    b = ValveSim("gripper-valve_reset", seed=11, render_quality="fast")
    try:
        frames_a, rewards_a = _episode(a, 0)
        frames_b, rewards_b = _episode(b, 0)
        assert rewards_a == rewards_b
        assert all(np.array_equal(x, y) for x, y in zip(frames_a, frames_b, strict=True))
        assert all(-1.0 <= r <= 0.0 for r in rewards_a)
        with pytest.raises(RuntimeError, match="reset"):
            a.step(np.zeros(4))
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("task", sim.TASKS)
def test_a_stand_in_restored_from_its_state_takes_the_same_path_bit_for_bit(task: str) -> None:
    """A resumed run must continue as if never stopped: in scenario 1 the valve and the fingers'
    pose carry over from one episode into the next, so the whole physics comes back."""
    a = ValveSim(task, seed=11, image_size=32, render_quality="fast")
    try:
        for seed in range(2):  # the fingers end anywhere, the valve moved and perhaps still turning
            _episode(a, seed)
        state = a.rng_state()
        b = ValveSim(task, seed=99, image_size=32, render_quality="fast")
        try:
            b.set_rng_state(state)
            for seed in (2, 3):
                frames_a, rewards_a = _episode(a, seed)
                frames_b, rewards_b = _episode(b, seed)
                assert rewards_a == rewards_b
                assert all(np.array_equal(x, y) for x, y in zip(frames_a, frames_b, strict=True))
                assert b.target_angle == a.target_angle
        finally:
            b.close()
        before = a.rng_state()
        with pytest.raises(ValueError, match="physics state has 3 values"):
            a.set_rng_state(dict(state, physics=[0.0, 0.0, 0.0]))
        with pytest.raises(ValueError, match="setpoints have shape"):
            a.set_rng_state(dict(state, setpoint=[0.0]))
        with pytest.raises(ValueError, match="not finite"):
            a.set_rng_state(dict(state, target_angle=float("nan")))
        assert a.rng_state() == before  # a refused state changes nothing
    finally:
        a.close()


def test_a_state_with_only_the_valve_angle_puts_the_valve_back_close() -> None:
    """A state without the physics (one that says only where the valve stands) still resumes:
    the valve comes back to within the reset servo's tolerance, not bit for bit."""
    a = ValveSim("gripper-valve_reset", seed=11, render_quality="fast")
    b = ValveSim("gripper-valve_reset", seed=11, render_quality="fast")
    try:
        _episode(a, 0)
        state = _angle_only(a.rng_state())
        a.reset()
        b.set_rng_state(state)
        b.reset()
        assert b.target_angle == a.target_angle
        assert angle_distance(b.valve_angle, a.valve_angle) < 2 * sim.VALVE_TOLERANCE
    finally:
        a.close()
        b.close()


def test_frames_are_uint8_chw_at_the_image_size_in_every_quality() -> None:
    for quality, size in (("fast", 84), ("paper", 48), ("plain", 64)):
        env = ValveSim("gripper-valve", seed=0, image_size=size, render_quality=quality)
        try:
            frame, reward, discount, last = env.reset()
            assert frame.shape == (3, size, size) and frame.dtype == np.uint8
            assert (reward, discount, last) == (0.0, 1.0, False)
            assert frame.std() > 10  # a scene, not a blank image
        finally:
            env.close()
    with pytest.raises(ValueError, match="render_quality"):
        ValveSim("gripper-valve", seed=0, render_quality="nice")  # type: ignore[arg-type]
    with pytest.raises(sim.UnknownGripperTask, match="gripper-valve_reset"):
        ValveSim("gripper-door", seed=0)


def _direction(frame: np.ndarray, mask: np.ndarray) -> float:
    """The angle of the masked pixels' centroid about the image centre, as the top camera sees
    the world (image right is +x, image up is +y)."""
    rows, cols = np.nonzero(mask)
    centre = (frame.shape[1] - 1) / 2
    return math.atan2(centre - rows.mean(), cols.mean() - centre)


def test_the_target_and_the_valve_angle_are_drawn_where_they_are_and_large_enough_for_32x32() -> None:
    """The policy sees only pixels: at 32x32 the green target bar and the red spoke must each
    cover several pixels, in the direction of their angle, with the fingers at home."""
    for quality in ("plain", "paper"):
        env = ValveSim("gripper-valve_reset", seed=1, image_size=32, render_quality=quality)
        try:
            for _ in range(8):
                frame, *_ = env.reset()
                r, g, b = frame.astype(int)
                green = (g > 150) & (r < 100) & (b < 120)
                red = (r > 150) & (g < 90) & (b < 90)
                assert green.sum() >= 10 and red.sum() >= 6, (quality, green.sum(), red.sum())
                assert math.degrees(angle_distance(_direction(frame, green), env.target_angle)) < 5
                assert math.degrees(angle_distance(_direction(frame, red), env.valve_angle)) < 5
        finally:
            env.close()


def test_action_repeat_shortens_the_episode() -> None:
    env = ValveSim("gripper-valve", seed=0, action_repeat=2, render_quality="fast")
    try:
        env.reset()
        steps, last = 0, False
        while not last:
            _, reward, _, last = env.step(np.zeros(4))
            steps += 1
            assert -2.0 <= reward <= 0.0
        assert steps == sim.EPISODE_STEPS // 2
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros(3))
    finally:
        env.close()


def test_restoring_a_state_puts_the_valve_back_exactly_wherever_the_fingers_were() -> None:
    """A state that gives only the valve's angle, restored with the fingers anywhere: they go
    home first, so the valve is never put into a finger and kicked away."""
    env = ValveSim("gripper-valve", seed=0, image_size=32, render_quality="fast")
    rng = np.random.default_rng(0)
    try:
        start = env.rng_state()
        for _ in range(8):
            env.reset()
            action = rng.uniform(-1, 1, 4)
            for _ in range(10):
                env.step(action)
            state = _angle_only(start)
            state["valve_angle"] = float(rng.uniform(0.0, 2.0 * math.pi))
            env.set_rng_state(state)
            env.reset()
            assert angle_distance(env.valve_angle, state["valve_angle"]) < math.radians(0.5)
    finally:
        env.close()
