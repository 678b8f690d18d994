"""Deterministic evaluation episodes, shared by the trainer and the evaluator service."""

from __future__ import annotations

import numpy as np

from shared.agents import Agent
from shared.env_loop import EnvLoop
from shared.envs import PixelEnv


def evaluate(agent: Agent, env: PixelEnv, episodes: int) -> list[float]:
    """Extrinsic return of each of `episodes` episodes with the deterministic policy."""
    unused = np.random.default_rng(0)  # explore=False draws nothing
    loop = EnvLoop(env)
    return [loop.run_episode(lambda obs: agent.act(obs, explore=False, rng=unused)) for _ in range(episodes)]
