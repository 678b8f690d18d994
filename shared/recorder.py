"""What a run records, the same for both runners: eval.csv, train.csv and the checkpoint's core.

`nasa train` and the learner service write their rows and checkpoints through
a `Recorder`, so a plot, a resume or a comparison never cares which runner
made a run. Each runner adds what only it has to the checkpoint (the trainer
its environments' random states, the learner its published policy version).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from shared import checkpoint
from shared.agents import Agent
from shared.runlog import TRAIN_FIELDS, CsvLog, eval_fields, older_eval_fields, read_rows

T = TypeVar("T")


@dataclass
class Counters:
    """The progress a checkpoint carries: env steps, finished episodes, training wall-clock."""

    env_steps: int = 0
    episodes: int = 0
    wall_s: float = 0.0


class MetricMeans:
    """Per-episode means of the update metrics that train.csv has a column for."""

    def __init__(self) -> None:
        self._sums: dict[str, float] = defaultdict(float)
        self._counts: dict[str, int] = defaultdict(int)

    def add(self, metrics: dict[str, float]) -> None:
        for key, value in metrics.items():
            if key in TRAIN_FIELDS:
                self._sums[key] += value
                self._counts[key] += 1

    def take(self) -> dict[str, float]:
        means = {k: self._sums[k] / self._counts[k] for k in self._sums}
        self._sums.clear()
        self._counts.clear()
        return means


class Recorder:
    def __init__(self, out: Path, eval_episodes: int) -> None:
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.eval_episodes = eval_episodes
        self.eval_log = CsvLog(self.out / "eval.csv", eval_fields(eval_episodes),
                               older=older_eval_fields(eval_episodes))
        self.train_log = CsvLog(self.out / "train.csv", TRAIN_FIELDS)

    def eval_row(self, step: int, returns: list[float], *, updates: int) -> dict:
        """Append one evaluation (each episode's extrinsic return, played by the weights of
        `updates` updates) and return its row."""
        returns = [float(r) for r in returns][: self.eval_episodes]
        row = {"step": int(step), "updates": int(updates), "mean": float(np.mean(returns)),
               "std": float(np.std(returns)), "min": min(returns), "max": max(returns)}
        row |= {f"return_{i}": r for i, r in enumerate(returns)}
        self.eval_log.append(row)
        return row

    def train_row(self, step: int, episode: int, episode_return: float, length: int, updates: int,
                  wall_s: float, means: dict[str, float], steps_per_s: float | None = None) -> dict:
        """Append one finished training episode; `means`: update metrics and intrinsic means."""
        row = {
            "step": int(step), "episode": int(episode), "return": float(episode_return),
            "length": int(length),
            "updates": int(updates), "steps_per_s": steps_per_s, "wall_s": float(wall_s),
            **{k: v for k, v in means.items() if k in TRAIN_FIELDS},
        }
        self.train_log.append(row)
        return row

    def last_eval(self) -> dict | None:
        """step, mean and std of the newest evaluation in eval.csv, or None."""
        return _newest(self.eval_log.path, lambda row: {
            "step": int(row["step"]), "mean": float(row["mean"]), "std": float(row["std"])})

    def last_episode(self) -> tuple[int, float] | None:
        """The number and wall-clock seconds of the newest episode in train.csv, or None."""
        return _newest(self.train_log.path, lambda row: (int(row["episode"]), float(row["wall_s"])))

    def checkpoint(self, path: Path, agent: Agent, rng: np.random.Generator, counters: Counters,
                   **extra: object) -> None:
        """Write a checkpoint: the agent, every random state, the counters, the CSV row counts, `extra`."""
        for log in (self.eval_log, self.train_log):
            log.sync()
        checkpoint.save(path, {
            "agent": agent.state_dict(),
            "rng": checkpoint.rng_state(rng),
            "env_steps": counters.env_steps,
            "episodes": counters.episodes,
            "wall_s": counters.wall_s,
            "eval_rows": self.eval_log.rows(),
            "train_rows": self.train_log.rows(),
            **extra,
        })

    def restore(self, state: dict, agent: Agent, rng: np.random.Generator, truncate: bool) -> Counters:
        """Load a checkpoint's agent and random states; with `truncate`, drop the CSV rows written
        after it (the trainer replays those steps exactly; the learner keeps what the fleet reported)."""
        try:
            agent.load_state_dict(state["agent"])
        except (KeyError, TypeError, ValueError) as err:
            raise checkpoint.CheckpointError(
                f"the checkpoint's agent does not fit this run's algorithm and settings: {err}") from err
        checkpoint.restore_rng_state(rng, state["rng"])
        if truncate:
            self.eval_log.truncate(int(state["eval_rows"]))
            self.train_log.truncate(int(state["train_rows"]))
        return Counters(int(state["env_steps"]), int(state["episodes"]), float(state["wall_s"]))

    def clear(self) -> None:
        """Drop every row (a run killed before its first checkpoint starts over)."""
        self.eval_log.truncate(0)
        self.train_log.truncate(0)


def _newest(path: Path, read: Callable[[dict], T]) -> T | None:
    """`read` of the newest row of a run log it can read (a damaged row: the one before it)."""
    for row in reversed(read_rows(path)):
        try:
            return read(row)
        except (KeyError, TypeError, ValueError):
            continue
    return None
