"""The update schedule: how many updates each env step makes, in `nasa train` and as the learner's
target and the replay's rate limit in `nasa up`.

After `warmup_steps` uniform random steps, each step makes G (`updates_per_step`) updates. With
`warmup_burst` (SAC-AE's reference), the first step after warm-up makes `warmup_steps` updates in
place of its G: SAC-AE's `train.py` makes `init_steps` updates at its step `init_steps` (counted
from 0, before that step's transition is stored), then one a step, so by the step whose count is N
it has made init_steps + (N - init_steps - 1) updates, as this schedule makes by step N. With
`updates_before_store` (SAC-AE's order too) a step's updates come before its transition is stored,
so each samples the transitions of the steps before it, as SAC-AE's do; without, after.
"""

from __future__ import annotations

from shared.config import TrainConfig


def burst_extra(config: TrainConfig) -> int:
    """The updates the warm-up burst makes beyond the G of its step (negative where the warm-up is
    shorter than G; 0 without the burst)."""
    return config.warmup_steps - config.updates_per_step if config.warmup_burst else 0


def step_updates(step: int, config: TrainConfig) -> int:
    """The updates env step `step` (counted from 1) makes: right after it, or with
    `updates_before_store` before its transition is stored."""
    if step <= config.warmup_steps:
        return 0
    return config.updates_per_step + (burst_extra(config) if step == config.warmup_steps + 1 else 0)


def updates_due(env_steps: int, config: TrainConfig) -> int:
    """The updates made once `env_steps` steps and their updates are done."""
    learning = env_steps - config.warmup_steps
    return config.updates_per_step * learning + burst_extra(config) if learning > 0 else 0


def stored_updates(stored: int, config: TrainConfig) -> int:
    """The updates the schedule makes on a replay of `stored` transitions: those due by step
    `stored`, and with `updates_before_store` the next step's, made before its transition is
    stored (the replay's rate limit)."""
    return updates_due(stored + 1 if config.updates_before_store else stored, config)


def first_update_rows(config: TrainConfig) -> int:
    """The transitions stored when the first update may sample (the rate limiter's minimum size):
    the warm-up's, and without `updates_before_store` the next step's; at least one (a warm-up of
    0 with its burst of 0 updates leaves the first update to the second step, on one)."""
    return max(1, config.warmup_steps + (0 if config.updates_before_store else 1))


def limiter_extra(config: TrainConfig) -> int:
    """The samples beyond G the rate limiter allows on its minimum size (first_update_rows): the
    schedule's updates on those rows less one step's G. SAC-AE's burst beyond G; with
    `updates_before_store` and no warm-up, the burst of 0 plus the second step's G, made on the one
    row the minimum size holds."""
    return stored_updates(first_update_rows(config), config) - config.updates_per_step


def total_updates(config: TrainConfig) -> int:
    """The run's updates."""
    return updates_due(config.steps, config)


def burst_updates(config: TrainConfig) -> int:
    """How many of the run's first updates the warm-up burst makes (0 without it): an updating
    agent's `burst_updates`."""
    return config.warmup_steps if config.warmup_burst else 0
