"""The one environment loop: the trainer, the actors, evaluation and the benchmarks step through it.

An `EnvLoop` steps a `PixelEnv` and hands every transition to an adder (the
replay store in process, the replay client's writer in an actor, none in
evaluation), with the discount the run stores (`stored_discount`). It keeps
the running episode's return and length; the caller chooses the actions and
decides what happens between steps (updates, weights, evaluation).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np

from shared.envs import PixelEnv, TimeStep, stored_discount

if TYPE_CHECKING:
    from shared.replay.adder import Adder


class EnvLoop:
    def __init__(self, env: PixelEnv, adder: Adder | None = None,
                 time_limit: Literal["bootstrap", "terminal"] | None = None) -> None:
        """`time_limit`: the run's `env.time_limit`, which decides the discounts stored; needed with
        an adder (the config holds the one default)."""
        if adder is not None and time_limit is None:
            raise TypeError("an EnvLoop that stores transitions needs the run's time_limit")
        self.env = env
        self.adder = adder
        self.time_limit = time_limit
        self.episode_return = 0.0
        self.episode_length = 0
        self.steps = 0  # over every episode
        self.last_step_s = 0.0  # the environment's time for the newest step (the adder's wait aside)

    def reset(self) -> TimeStep:
        """Begin an episode (the adder gets its first frame)."""
        ts = self.env.reset()
        self.episode_return, self.episode_length = 0.0, 0
        if self.adder is not None:
            self.adder.add_first(ts.frame)
        return ts

    def step(self, action: np.ndarray, policy_version: int = 0) -> TimeStep:
        """One environment step; the transition goes to the adder with the policy version that chose it."""
        start = time.perf_counter()
        ts = self.env.step(action)
        self.last_step_s = time.perf_counter() - start
        self.episode_return += ts.reward
        self.episode_length += 1
        self.steps += 1
        if self.adder is not None:
            discount = stored_discount(ts, self.time_limit)
            self.adder.add(action, ts.reward, discount, ts.frame, ts.last, policy_version)
        return ts

    def run_episode(self, act: Callable[[np.ndarray], np.ndarray]) -> float:
        """A whole episode with `act(obs) -> action`; returns its extrinsic return."""
        ts = self.reset()
        while not ts.last:
            ts = self.step(act(ts.obs))
        return self.episode_return
