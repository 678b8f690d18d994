"""Deterministic evaluation episodes, shared by the trainer and the evaluator service."""

from __future__ import annotations

import numpy as np

from shared.agents import Agent
from shared.envs import PixelEnv


def evaluate(agent: Agent, env: PixelEnv, episodes: int) -> list[float]:
    """Extrinsic return of each of `episodes` episodes with the deterministic policy."""
    unused = np.random.default_rng(0)  # explore=False draws nothing
    returns = []
    for _ in range(episodes):
        ts = env.reset()
        total = 0.0
        while not ts.last:
            ts = env.step(agent.act(ts.obs, explore=False, rng=unused))
            total += ts.reward
        returns.append(total)
    return returns
