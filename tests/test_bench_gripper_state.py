"""bench.gripper_state: the stand-in's true state, and TD3 learning from it with the project's update."""

import math
import subprocess
import sys

import numpy as np
import pytest

from bench.gripper_state import STATE_DIM, StateValve, state_agent, train


def test_the_state_holds_the_valve_the_target_and_the_fingers():
    env = StateValve("gripper-valve_reset", 3)
    env.reset()
    env.step(np.array([0.5, -0.5, 0.2, 0.0]))
    s = env.state()
    assert s.shape == (STATE_DIM,) and s.dtype == np.float32
    assert np.allclose(s[:4], [math.cos(env.valve_angle), math.sin(env.valve_angle),
                               math.cos(env.target_angle), math.sin(env.target_angle)], atol=1e-6)
    difference = env.target_angle - env.valve_angle
    assert np.allclose(s[4:6], [math.cos(difference), math.sin(difference)], atol=1e-6)
    assert np.allclose(s[6:10], env.data.qpos[env._finger_qpos], atol=1e-6)
    env.close()


def test_without_the_difference_the_state_holds_what_a_frame_shows():
    full, bare = StateValve("gripper-valve", 3), StateValve("gripper-valve", 3, difference=False)
    for env in (full, bare):
        env.reset()
        env.step(np.array([0.5, -0.5, 0.2, 0.0]))
    assert bare.state_dim == STATE_DIM - 2 and bare.state().shape == (STATE_DIM - 2,)
    assert np.array_equal(bare.state(), np.delete(full.state(), [4, 5]))  # same draws, less state
    result = train(steps=30, eval_every=30, seed=0, eval_episodes=1, warmup=20, difference=False)
    assert result["updates"] == 10
    full.close()
    bare.close()


def test_angle_noise_blurs_the_reading_of_both_angles_and_not_the_stand_in():
    exact, noisy = StateValve("gripper-valve", 4), StateValve("gripper-valve", 4, angle_noise=15.0)
    errors = []
    for env in (exact, noisy):
        env.reset()
    for i in range(200):
        action = np.array([0.6, -0.6, 0.3, -0.1]) * (-1) ** (i // 10)
        for env in (exact, noisy):
            if env.step(action)[3]:
                env.reset()
        assert noisy.valve_angle == exact.valve_angle and noisy.target_angle == exact.target_angle
        read = noisy.state()
        for k, angle in ((0, noisy.valve_angle), (2, noisy.target_angle)):
            errors.append(math.remainder(math.atan2(read[k + 1], read[k]) - angle, 2 * math.pi))
        assert np.allclose(read[6:], exact.state()[6:])  # the fingers are read exactly
    assert 12.0 < math.degrees(np.std(errors)) < 18.0
    exact.close()
    noisy.close()


def test_the_valve_joint_can_be_made_freer_or_stiffer_and_the_same_actions_turn_it_more_or_less():
    def turned(**valve: float) -> tuple[tuple[float, float], float]:
        env = StateValve("gripper-valve", 5, **valve)
        index = env._valve_dof
        params = (float(env.model.dof_frictionloss[index]), float(env.model.dof_damping[index]))
        env.reset()
        total, before = 0.0, env.valve_angle
        rng = np.random.default_rng(0)
        for _ in range(50):
            env.step(rng.uniform(-1, 1, 4))
            total += abs(math.remainder(env.valve_angle - before, 2 * math.pi))
            before = env.valve_angle
        env.close()
        return params, total

    (friction, damping), as_built = turned()
    assert (friction, damping) == (0.01, 0.005)  # the model's, as --help says
    (friction, damping), free = turned(valve_friction=0.0005, valve_damping=0.001)
    assert (friction, damping) == (0.0005, 0.001)
    _, stiff = turned(valve_friction=0.2)
    assert free > as_built > stiff


def test_a_short_run_updates_after_the_warm_up_and_evaluates_on_schedule():
    result = train(steps=60, eval_every=30, seed=0, eval_episodes=1, warmup=20)
    assert list(result["evals"]) == ["0", "30", "60"]
    assert result["updates"] == 40  # one per step after the warm-up (G = 1)
    assert all(-50.0 <= v <= 0.0 for v in result["evals"].values())


def test_settings_over_cpu_small_reach_the_agent_and_g_updates_follow_each_step():
    result = train(steps=30, eval_every=30, seed=0, eval_episodes=1, warmup=20,
                   agent_settings={"gamma": 0.5}, updates_per_step=3)
    assert result["updates"] == 30  # three per step after the warm-up
    agent, _ = state_agent(0, {"gamma": 0.5, "exploration_noise": 0.3})
    assert agent.config.gamma == 0.5 and agent.config.exploration_noise == 0.3
    with pytest.raises(ValueError, match="unknown agent setting"):
        state_agent(0, {"gama": 0.5})


BAD = [["--steps", "0"], ["--eval-every", "-5"], ["--seed", "-1"], ["--steps", "nan"],
       ["--updates-per-step", "0"], ["--gamma", "x"], ["--threads", "0"], ["--angle-noise", "-1"],
       ["--angle-noise", "nan"], ["--valve-friction", "-0.01"], ["--valve-damping", "nan"],
       ["--valve-friction", "inf"]]


@pytest.mark.parametrize("bad", BAD)
def test_bad_arguments_are_one_clear_error(bad):
    done = subprocess.run([sys.executable, "-m", "bench.gripper_state", *bad], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "error:" in done.stderr
