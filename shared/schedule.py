"""The update schedule: how many updates each env step makes, in `nasa train` and as the learner's
target and the replay's rate limit in `nasa up`.

After `warmup_steps` uniform random steps, each step makes G (`updates_per_step`) updates. With
`warmup_burst` (SAC-AE's reference), the first step after warm-up makes `warmup_steps` updates in
place of its G: SAC-AE's `train.py` makes `init_steps` updates at its step `init_steps` (counted
from 0, before that step's transition is stored), then one a step, so by the step whose count is N
it has made init_steps + (N - init_steps - 1) updates, as this schedule makes by step N.
"""

from __future__ import annotations

from shared.config import TrainConfig


def burst_extra(config: TrainConfig) -> int:
    """The updates the warm-up burst makes beyond the G of its step (negative where the warm-up is
    shorter than G; 0 without the burst)."""
    return config.warmup_steps - config.updates_per_step if config.warmup_burst else 0


def step_updates(step: int, config: TrainConfig) -> int:
    """The updates made right after env step `step` (counted from 1)."""
    if step <= config.warmup_steps:
        return 0
    return config.updates_per_step + (burst_extra(config) if step == config.warmup_steps + 1 else 0)


def updates_due(env_steps: int, config: TrainConfig) -> int:
    """The updates made once `env_steps` steps and their updates are done."""
    learning = env_steps - config.warmup_steps
    return config.updates_per_step * learning + burst_extra(config) if learning > 0 else 0


def total_updates(config: TrainConfig) -> int:
    """The run's updates."""
    return updates_due(config.steps, config)


def burst_updates(config: TrainConfig) -> int:
    """How many of the run's first updates the warm-up burst makes (0 without it): an updating
    agent's `burst_updates`."""
    return config.warmup_steps if config.warmup_burst else 0
