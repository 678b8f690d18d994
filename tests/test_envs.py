"""The environment seam: EnvSpec, sources chosen by task name, a spec without rendering, any channel count."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from shared import envs
from shared.config import EnvConfig


class GreyPixels:
    """A one-channel stand-in environment: frame t is filled with t; ends after 4 steps."""

    def __init__(self, size: int) -> None:
        self.frame_shape = (1, size, size)
        self.action_dim = 2
        self.t = 0

    def _frame(self) -> np.ndarray:
        return np.full(self.frame_shape, self.t, np.uint8)

    def reset(self):  # noqa: ANN201
        self.t = 0
        return self._frame(), 0.0, 1.0, False

    def step(self, action):  # noqa: ANN001, ANN201
        self.t += 1
        return self._frame(), 1.0, 1.0, self.t == 4

    def rng_state(self) -> dict:
        return {}

    def set_rng_state(self, state: dict) -> None:
        pass


@dataclass
class GreySource:
    name: str = "grey"
    made: int = 0

    def tasks(self) -> list[str]:
        return ["grey-one", "grey-two"]

    def spec(self, config: EnvConfig) -> envs.EnvSpec:
        return envs.EnvSpec((1, config.image_size, config.image_size), config.frame_stack, 2)

    def make(self, config: EnvConfig, seed: int) -> envs.PixelEnv:
        self.made += 1
        return envs.FrameStack(GreyPixels(config.image_size), config.frame_stack)


@pytest.fixture
def grey():
    before = list(envs._SOURCES)
    source = envs.register(GreySource())
    yield source
    envs._SOURCES[:] = before


def test_env_spec_shapes_and_round_trip():
    spec = envs.EnvSpec((3, 84, 84), 3, 6)
    assert spec.obs_shape == (9, 84, 84)
    assert envs.EnvSpec((1, 16, 16), 4, 1).obs_shape == (4, 16, 16)
    back = envs.EnvSpec.from_dict(spec.to_dict())
    assert back == spec and isinstance(back.frame_shape, tuple)
    assert envs.EnvSpec([3, 84, 84], 3, 6) == spec  # a list (from JSON) compares equal
    with pytest.raises(ValueError, match="frame_shape"):
        envs.EnvSpec((84, 84), 3, 6)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=">= 1"):
        envs.EnvSpec((3, 84, 84), 0, 6)


def test_dmc_spec_reads_the_action_size_without_rendering(monkeypatch):
    from dm_control.mujoco import Physics

    def no_render(*args, **kwargs):
        raise AssertionError("spec() rendered a frame")

    monkeypatch.setattr(Physics, "render", no_render)
    config = EnvConfig(task="cheetah-run", image_size=48, frame_stack=2)
    spec = envs.spec(config)
    assert spec == envs.EnvSpec((3, 48, 48), 2, 6)


def test_the_built_environment_has_the_spec_of_its_config():
    config = EnvConfig(task="reacher-hard", image_size=16, render_quality="fast")
    env = envs.from_config(config, seed=0)
    assert env.spec == envs.spec(config)
    assert env.obs_shape == env.spec.obs_shape and env.action_dim == env.spec.action_dim == 2
    ts = env.reset()
    assert ts.obs.shape == env.spec.obs_shape and ts.frame.shape == env.spec.frame_shape


def test_a_second_source_is_one_registered_object(grey):
    config = EnvConfig(task="grey-two", image_size=8, frame_stack=3)
    envs.check_task("grey-two")
    assert envs.spec(config) == envs.EnvSpec((1, 8, 8), 3, 2)
    env = envs.from_config(config, seed=0)
    assert grey.made == 1 and env.spec == envs.spec(config)
    # Frames of one channel stack to k channels: no 3-channel assumption.
    ts = env.reset()
    assert ts.obs.shape == (3, 8, 8)
    nxt = env.step(np.zeros(2))
    assert nxt.obs.shape == (3, 8, 8) and list(nxt.obs[:, 0, 0]) == [0, 0, 1]
    assert envs.source_for("cartpole-balance").name == "dmc"
    assert envs.source_for("grey-one") is grey


def test_an_unknown_task_lists_the_names_of_every_source(grey):
    with pytest.raises(envs.UnknownTaskError) as err:
        envs.check_task("cartpole-juggle")
    message = str(err.value)
    assert message.startswith("unknown task 'cartpole-juggle'; valid tasks are: ")
    for name in ("cartpole-balance", "cheetah-run", "grey-one", "grey-two"):
        assert name in message
    with pytest.raises(envs.UnknownTaskError):
        envs.spec(EnvConfig(task="grey-three"))
    with pytest.raises(ValueError, match="already registered"):
        envs.register(GreySource())


def test_a_dmc_task_name_of_another_source_is_not_a_suite_task(grey):
    with pytest.raises(envs.UnknownTaskError, match="not a DeepMind Control Suite task"):
        envs.parse_task("grey-one")
    assert envs.parse_task("ball_in_cup-catch") == ("ball_in_cup", "catch")


RENDER_AND_REPORT = """
import hashlib, os, numpy as np
from shared.envs import DMCPixels
env = DMCPixels("ball_in_cup-catch", 0, 64, 0, 2, "fast")
env._env.reset()
digest = hashlib.sha256()
for action in np.linspace(-1, 1, 10):
    env._env.step([action, -action])
    digest.update(env.render().tobytes())
threads = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
print(digest.hexdigest(), sum(name.startswith("llvmpipe") for name in threads), os.environ["LP_NUM_THREADS"])
"""


def test_software_gl_draws_in_the_calling_thread_by_default_and_the_same_pixels_as_with_threads():
    def run(**env: str) -> list[str]:
        base = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
        out = subprocess.run([sys.executable, "-c", RENDER_AND_REPORT], env={**base, **env},
                             cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    default, threaded = run(), run(LP_NUM_THREADS="2")  # a value the user sets is kept
    assert default[1:] == ["0", "0"]  # no rasterizer threads of Mesa's beside the caller
    assert threaded[2] == "2"
    assert default[0] == threaded[0]  # the same frames, drawn either way


def test_a_suite_task_renders_with_one_camera_the_pixels_a_fresh_camera_draws():
    env = envs.DMCPixels("cartpole-swingup", 0, 48, 0, 1, "fast")
    env.reset()
    for action in np.linspace(-1, 1, 5):
        frame, *_ = env.step(np.array([action], dtype=np.float32))
        fresh = env._env.physics.render(48, 48, camera_id=0).transpose(2, 0, 1)
        assert np.array_equal(frame, fresh)


def test_a_ctrl_c_while_the_renderer_is_made_waits_until_it_is_made(monkeypatch):
    """An interrupt inside the GL context's making left half a context, whose teardown printed a
    traceback of its own after the run's stop message."""
    import signal
    import time

    import dm_control.mujoco

    from shared.envs import DMCPixels

    made = []

    class Camera:
        def __init__(self, physics, height, width, camera_id):
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C, while the context is being made
            time.sleep(0.05)
            made.append(self)

        def render(self):
            return np.zeros((32, 32, 3), np.uint8)

    monkeypatch.setattr(dm_control.mujoco, "Camera", Camera)
    env = DMCPixels("cartpole-swingup", 0, image_size=32)
    with pytest.raises(KeyboardInterrupt):
        env.render()
    assert made and env._camera is made[0]


def test_an_initial_state_the_simulation_cannot_hold_is_drawn_again_and_then_is_an_env_fault():
    from dm_control.rl.control import PhysicsError

    env = envs.DMCPixels("cartpole-balance", seed=0, image_size=16)
    suite, reset = env._env, env._env.reset
    failures = [1]

    def unstable() -> object:
        if failures[0] > 0:
            failures[0] -= 1
            reset()  # the draw happens, then the state is refused
            raise PhysicsError("Physics state is invalid. Warning(s) raised: mjWARN_BADQACC")
        return reset()

    suite.reset = unstable
    frame, reward, discount, last = env.reset()
    assert frame.shape == (3, 16, 16) and not last
    failures[0] = envs.RESET_TRIES
    with pytest.raises(envs.EnvFault, match="diverged at each of 3 resets"):
        env.reset()
