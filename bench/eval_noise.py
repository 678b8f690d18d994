"""How much of a "time to 700" is the evaluation's own noise?

A run evaluated with many episodes per evaluation (`nasa train ... --eval-episodes 50`) gives,
at each evaluation step, a sample of its policy's returns. From it this reads off what an
evaluation of fewer episodes (`--episodes`, the preset's 5) would have reported for the same
policy: the chance that its mean reaches `--goal`, and, for the run's sequence of policies,
the distribution of the first evaluation step at which a run of that evaluation size would
have reported the goal. On a sparse task, where each episode either catches (about 1,000)
or not (0), a policy that catches in 3 of 5 episodes on average reads 700 or more in about
one evaluation of three; this says how much of the goal's crossing step is that draw rather
than the learning.

    python -m bench.eval_noise RUN_DIR [--episodes 5] [--goal 700] [--resamples 100000]

Each evaluation step is resampled from its own returns (with replacement), independently of
the others: the policies stay the run's, only the evaluation episodes are drawn again. The
last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from shared.runlog import read_rows


def returns_by_step(eval_csv: Path) -> list[tuple[int, np.ndarray]]:
    """(step, each episode's return) of every row of an eval.csv."""
    rows = read_rows(eval_csv)
    out = []
    for row in rows:
        values = [float(v) for k, v in row.items() if k.startswith("return_") and v not in ("", None)]
        if values:
            out.append((int(row["step"]), np.asarray(values)))
    return out


def chance_of_goal(returns: np.ndarray, episodes: int, goal: float, resamples: int,
                   rng: np.random.Generator) -> float:
    """The chance that the mean of `episodes` returns drawn from `returns` reaches `goal`."""
    draws = rng.choice(returns, size=(resamples, episodes), replace=True)
    return float(np.mean(draws.mean(axis=1) >= goal))


def first_goal_distribution(chances: list[float]) -> tuple[list[float], float]:
    """For independent evaluations with these chances of reading the goal: the probability that
    each one is the first to read it, and that none does."""
    first, none_yet = [], 1.0
    for p in chances:
        first.append(none_yet * p)
        none_yet *= 1.0 - p
    return first, none_yet


def analyse(rows: list[tuple[int, np.ndarray]], episodes: int, goal: float, resamples: int,
            seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    steps, means, chances, per_step = [], [], [], []
    for step, returns in rows:
        n = len(returns)
        mean = float(returns.mean())
        half_width = 1.96 * float(returns.std(ddof=1)) / math.sqrt(n) if n > 1 else None
        chance = chance_of_goal(returns, episodes, goal, resamples, rng)
        steps.append(step)
        means.append(mean)
        chances.append(chance)
        per_step.append({"step": step, "episodes": n, "mean": round(mean, 1),
                         "ci95": round(half_width, 1) if half_width is not None else None,
                         "chance_of_goal": round(chance, 4)})
    # From the values as computed: the rounded ones printed would read 699.96 as the goal of 700.
    first, never = first_goal_distribution(chances)
    cumulative = list(np.cumsum(first)) if first else []

    def quantile_step(q: float) -> int | None:
        return next((s for s, c in zip(steps, cumulative, strict=True) if c >= q), None)

    return {
        "episodes_per_evaluation": episodes,
        "goal": goal,
        "per_step": per_step,
        "first_step_mean_at_goal": next((s for s, m in zip(steps, means, strict=True) if m >= goal), None),
        "chance_goal_read_by_last_step": round(1.0 - never, 4),
        "median_first_goal_step": quantile_step(0.5),
        "first_goal_step_quartiles": [quantile_step(0.25), quantile_step(0.75)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder (or its eval.csv)")
    parser.add_argument("--episodes", type=int, default=5, help="episodes of the evaluation to read off")
    parser.add_argument("--goal", type=float, default=700.0)
    parser.add_argument("--resamples", type=int, default=100_000)
    args = parser.parse_args()
    if args.episodes < 1 or args.resamples < 1:
        parser.error("--episodes and --resamples must be at least 1")
    path = args.run / "eval.csv" if args.run.is_dir() else args.run
    if not path.is_file():
        parser.error(f"{path} is not a file: give a run folder with an eval.csv")
    rows = returns_by_step(path)
    if not rows:
        parser.error(f"{path} has no evaluation with episode returns")
    result = analyse(rows, args.episodes, args.goal, args.resamples)
    for r in result["per_step"]:
        ci = f" +- {r['ci95']:.0f}" if r["ci95"] is not None else ""
        chance = r["chance_of_goal"]
        print(f"step {r['step']:>7}: mean of {r['episodes']} episodes {r['mean']:7.1f}{ci}; a "
              f"{args.episodes}-episode evaluation reads >= {args.goal:g} with chance {chance:.3f}")
    print(json.dumps({"run": str(args.run), **result}))


if __name__ == "__main__":
    main()
