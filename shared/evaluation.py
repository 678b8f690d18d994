"""Deterministic evaluation episodes, shared by the trainer, the evaluator service and the learner
(which evaluates between its updates where `nasa up`'s layout says so)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shared.agents import Agent
from shared.config import TrainConfig
from shared.env_loop import EnvLoop
from shared.envs import PixelEnv
from shared.schedule import total_updates


def evaluate(agent: Agent, env: PixelEnv, episodes: int,
             act: Callable[[np.ndarray], np.ndarray] | None = None) -> list[float]:
    """Extrinsic return of each of `episodes` episodes with the deterministic policy (`act`, when
    given, is that policy wrapped: the evaluator's checks its stop flag before each step)."""
    if act is None:
        act = deterministic_policy(agent)
    loop = EnvLoop(env)
    return [loop.run_episode(act) for _ in range(episodes)]


def deterministic_policy(agent: Agent) -> Callable[[np.ndarray], np.ndarray]:
    """The agent's action without exploration noise."""
    unused = np.random.default_rng(0)  # explore=False draws nothing
    return lambda obs: agent.act(obs, explore=False, rng=unused)


def draws_restarter(env: PixelEnv, same_episodes: bool) -> Callable[[], None]:
    """What to call before each evaluation on `env` (just made): with `same_episodes`, it puts
    the environment's draws back where they stand now, so every evaluation plays the same
    episodes; without, nothing. A robot bridge's draws live in the bridge, which is asked to
    rewind them to where they stood when it started."""
    if not same_episodes:
        return lambda: None
    pixels = getattr(env, "pixels", env)
    rewind = getattr(pixels, "rewind_draws", None)
    if rewind is not None:
        return rewind
    start = env.rng_state()
    return lambda: env.set_rng_state(start)


def is_eval_step(step: int, config: TrainConfig) -> bool:
    """The run evaluates at each multiple of eval_every and at the end of its step budget (the
    final policy's, also where the budget is no multiple), step 0 only with eval_at_start."""
    if step == 0:
        return config.eval_at_start
    return 0 < step <= config.steps and (step % config.eval_every == 0 or step == config.steps)


def newest_eval_step(env_steps: int, config: TrainConfig) -> int:
    """The newest eval step reached at `env_steps` (0 before the first; see is_eval_step)."""
    if env_steps >= config.steps:
        return config.steps
    return (env_steps // config.eval_every) * config.eval_every


def final_eval_waits(step: int, config: TrainConfig, updates: int, final: bool) -> bool:
    """Whether eval step `step` must wait for more updates: the budget's own is the final policy's,
    played once every update of the run is made (or, `final`, once the learner has made all it
    will), as `nasa train` plays it after its last step's updates. The actors reach the budget
    before a distributed learner's last updates are made."""
    return step == config.steps > 0 and not final and updates < total_updates(config)


def eval_due(env_steps: int, config: TrainConfig, done: int) -> int | None:
    """The eval step to evaluate now: the newest eval step reached, if newer than `done` (-1:
    nothing evaluated yet, so step 0 is due). Steps between are skipped when evaluating is slower
    than training."""
    target = newest_eval_step(env_steps, config)
    return target if target > done else None


def first_done(config: TrainConfig) -> int:
    """`done` before any evaluation: -1 makes step 0 due (eval_at_start), 0 skips it."""
    return -1 if config.eval_at_start else 0
