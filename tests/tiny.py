"""Tiny settings for unit tests: 32 px frames, narrow nets, fast rendering, short warm-up."""

from __future__ import annotations

from shared.config import TrainConfig, default_config
from shared.envs import EnvSpec
from shared.run_config import RunConfig

WARMUP = 20


def tiny_config(algo: str = "nasa_td3", **overrides: object) -> TrainConfig:
    c = default_config(algo, "cpu-small", "cartpole-balance")
    c.env.task = "cartpole-balance"  # one action dimension, the cheapest suite task to render
    c.device = "cpu"
    c.warmup_steps = WARMUP
    c.batch_size = 16
    c.eval_every = 50
    c.eval_episodes = 2
    c.replay_capacity = 1000
    c.env.image_size = 32
    c.env.render_quality = "fast"
    c.agent.hidden_dim = 32
    c.agent.latent_dim = 16
    c.agent.ensemble_hidden_dim = 16
    c.agent.num_filters = 8
    for key, value in overrides.items():
        setattr(c, key, value)
    return c


def tiny_run(algo: str = "nasa_td3", **overrides: object) -> RunConfig:
    """A RunConfig for cartpole-balance (action dim 1) without building the environment."""
    return RunConfig(tiny_config(algo, **overrides), EnvSpec((3, 32, 32), 3, 1))


def tiny_gripper_run(algo: str = "td3_ae", **overrides: object) -> RunConfig:
    """A RunConfig for the gripper stand-in (action dim 4) at one action per step, for a client of
    a robot bridge that serves `ValveSim("gripper-valve", ..., image_size=32)`."""
    c = tiny_config(algo, **overrides)
    c.env.task, c.env.action_repeat = "gripper-valve", 1
    return RunConfig(c, EnvSpec((3, 32, 32), 3, 4))
