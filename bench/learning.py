"""Does it learn? The cpu-small preset on the headline task, bounded by wall-clock time.

Runs `nasa train` (single process) and then `nasa up` (the distributed system,
in the layout it chooses for this machine, as the README's main command) with
the cpu-small preset, each for at most --minutes of wall-clock time, reads each
run's eval.csv and reports the untrained policy's return (the evaluation at
step 0), the best and the last return, and the wall-clock time from the
launch (start-up and the step-0 evaluation included, as a user waits) until
an evaluation row with a mean return of 700 is written. The headline task,
ball_in_cup-catch, has a sparse reward: the untrained policy scores low
there (the ball falls into the cup by chance now and then). Goals on a 2-core CPU:
`nasa up` reaches 700 within 30 minutes, in at most 1.1x the time `nasa train`
takes (`up_vs_train_time_to_goal`).

One seed of a sparse task decides little: `--seed 0,1,2` runs both runners
for each seed in turn (train, then up, so a slower hour costs both alike) and
adds, per runner, how many seeds reached the goal, the median best and last
returns, and the median time to the goal of the seeds that reached it.

    python -m bench.learning [--task T] [--seed S[,S...]] [--minutes 30] [--up-minutes M]
                             [--out bench-results/learning] [--only train|up] [--report] [-- SETTINGS]

SETTINGS are `nasa train` flags passed to both runs after the preset's and its variant for
the task (cpu-small's gripper variant: one action per step, 20 evaluation episodes every
2,000 steps), e.g. `-- --eval-same-episodes`.

The last line is one JSON object. `nasa plot <out>` draws the curves.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import time
from contextlib import nullcontext
from pathlib import Path

from bench.args import task_name
from bench.processes import stop_group, stopped_cleanly
from nasa.layout import usable_cores
from nasa.up import free_port
from shared.faults import RunFolderError, lock_run
from shared.runlog import eval_walls, read_rows
from shared.service import followed

TASK = "ball_in_cup-catch"
ALGO = "nasa_td3"
GOAL = 700.0


def run_bounded(argv: list[str], minutes: float, log: Path, eval_csv: Path | None = None,
                poll_s: float = 1.0) -> tuple[float, dict[int, float]]:
    """Run a command until it ends or the time is up; returns the wall-clock used, and for each
    evaluation row of `eval_csv`, the seconds from the launch at which it was first seen.

    Both runners are timed from their launch, start-up and the step-0 evaluation included, as a
    user waits for them (each run's own clock starts elsewhere). At the bound it gets SIGINT (a
    user's Ctrl-C), then SIGTERM: a process started in the background by a non-interactive shell
    ignores SIGINT. Should this process die by SIGKILL, the command gets SIGTERM and stops its run
    (NASA_PARENT_PID: `shared.service.followed`).
    """
    start = time.monotonic()
    seen: dict[int, float] = {}
    with open(log, "w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                env=followed())
        try:
            while proc.poll() is None and time.monotonic() - start < minutes * 60:
                time.sleep(poll_s)
                if eval_csv is not None:
                    note_rows(eval_csv, seen, time.monotonic() - start)
        finally:  # at the bound, and on Ctrl-C or SIGTERM: in its own session, no signal reaches it
            stop_group(proc)
        if eval_csv is not None:  # rows written while it stopped: seen now, past the bound
            note_rows(eval_csv, seen, time.monotonic() - start)
    return time.monotonic() - start, seen


def note_rows(eval_csv: Path, seen: dict[int, float], now_s: float) -> None:
    """Record `now_s` for each complete row of `eval_csv` not seen before (by its step)."""
    try:
        text = eval_csv.read_text()
    except OSError:  # not written yet
        return
    for line in text.splitlines(keepends=True)[1:]:
        if not line.endswith("\n"):  # a row still being written
            break
        step = line.split(",", 1)[0]
        if step.isdigit():
            seen.setdefault(int(step), round(now_s, 1))


def summarize(run: Path, wall_s: float, bound_s: float, seen: dict[int, float]) -> dict:
    """Evaluation returns over steps, each with the seconds from the launch at which its row was
    written (`seen`, see run_bounded) and the run's own clock at that step (train.csv's wall_s:
    the end of the first episode at or after it; that clock starts after the start-up, and in
    `nasa train` after the step-0 evaluation). The goal time is from the launch and counts only
    within the bound."""
    rows = read_rows(run / "eval.csv") if (run / "eval.csv").exists() else []
    walls = eval_walls(run, [int(r["step"]) for r in rows])

    def wall_at(step: int) -> float | None:
        return round(walls[step], 1) if step in walls else None

    curve = [[int(r["step"]), round(float(r["mean"]), 1), seen.get(int(r["step"])), wall_at(int(r["step"]))]
             for r in rows]
    within = [(s, m, t) for s, m, t, _ in curve if t is not None and t <= bound_s]
    # The goal from the means as written: rounded, 699.96 would read as 700.
    means = {int(r["step"]): float(r["mean"]) for r in rows}
    reached = next(((s, t) for s, _, t in within if means[s] >= GOAL), None)
    return {
        "evals_step_mean_launch_s_run_s": curve,
        "wall_s": round(wall_s, 1),
        "untrained": curve[0][1] if curve else None,
        "best_within_bound": max((m for _, m, _ in within), default=None),
        "final_within_bound": within[-1][1] if within else None,
        "first_goal_step": reached[0] if reached else None,
        "first_goal_launch_s": reached[1] if reached else None,
        "goal_met": reached is not None,
    }


def launch(argv: list[str], out: Path, minutes: float, log: Path, report_only: bool) -> dict:
    """Start a fresh run in `out` and summarize it; with --report, only summarize the last one (from
    the times its launch saved beside the log)."""
    times = log.with_suffix(".evals.json")
    if report_only:
        wall, seen = load_times(times)
        return summarize(out, wall, minutes * 60, seen)
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    print("running:", " ".join(argv[2:]), flush=True)
    wall, seen = run_bounded(argv, minutes, log, out / "eval.csv")
    try:
        times.write_text(json.dumps({"wall_s": round(wall, 1), "seen": seen}))
    except OSError as err:  # a full disk must not cost the run's summary
        print(f"bench.learning: could not save {times} ({err}); --report will lack the launch times",
              file=sys.stderr, flush=True)
    return summarize(out, wall, minutes * 60, seen)


def load_times(path: Path) -> tuple[float, dict[int, float]]:
    """The wall-clock and launch times a run saved (none if it saved none); a clear error if the
    file is not what launch() writes."""
    if not path.exists():
        return 0.0, {}
    try:
        saved = json.loads(path.read_text())
        return float(saved["wall_s"]), {int(k): float(v) for k, v in saved["seen"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise SystemExit(f"bench.learning: {path} is not a file of launch times ({err!r}); "
                         "run the benchmark again without --report") from err


def seed_list(text: str) -> list[int]:
    """`0` or `0,1,2`: the seeds to run, each once, in the given order."""
    try:
        seeds = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seeds such as 0 or 0,1,2, got {text!r}") from None
    if len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"seeds must be distinct and >= 0, got {text!r}")
    return seeds


def median(values: list) -> float | None:
    """The median of the values that are not None (None if there are none)."""
    values = [v for v in values if v is not None]
    return round(statistics.median(values), 3) if values else None


def across_seeds(summaries: list[dict]) -> dict:
    """One runner over its seeds: how many reached the goal, and medians of the rest."""
    return {
        "seeds": len(summaries),
        "goal_reached": sum(s["goal_met"] for s in summaries),
        "best_median": median([s["best_within_bound"] for s in summaries]),
        "final_median": median([s["final_within_bound"] for s in summaries]),
        "first_goal_launch_s_median": median([s["first_goal_launch_s"] for s in summaries]),
    }


def split_settings(argv: list[str]) -> tuple[list[str], list[str]]:
    """This benchmark's flags, and the `nasa train` settings after `--` (passed to both runs)."""
    if "--" not in argv:
        return argv, []
    i = argv.index("--")
    return argv[:i], argv[i + 1 :]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--minutes", type=float, default=30.0, help="wall-clock bound of the nasa train run")
    parser.add_argument(
        "--up-minutes", type=float, default=None, help="bound of the nasa up run (default: --minutes)"
    )
    parser.add_argument(
        "--steps", type=int, default=100_000, help="step budget; the clock usually ends first"
    )
    parser.add_argument("--out", type=Path, default=Path("bench-results/learning"))
    parser.add_argument("--only", choices=("train", "up"), default=None)
    parser.add_argument("--seed", type=seed_list, default=[0], help="a seed, or several: 0,1,2")
    parser.add_argument("--task", type=task_name, default=TASK, help="the task (default: the headline task)")
    parser.add_argument("--report", action="store_true", help="only summarize the runs already in --out")
    own, settings = split_settings(sys.argv[1:])
    args = parser.parse_args(own)
    result: dict = {"task": args.task, "algo": ALGO, "preset": "cpu-small", "minutes": args.minutes,
                    "goal": GOAL, "cores": usable_cores(), "machine": platform.node(), "settings": settings,
                    "seeds": args.seed}
    runners = ("train", "up") if args.only is None else (args.only,)
    # Each launch clears its run folders first: a second launch on the same --out must not clear the
    # runs of one under way. A report only reads.
    try:
        held = nullcontext() if args.report else lock_run(args.out, "python -m bench.learning", "--out")
    except RunFolderError as err:  # held by another launch, or not writable
        raise SystemExit(f"bench.learning: {err}") from None
    with held:
        runs = [run_seed(args, seed, settings, runners) for seed in args.seed]
    if len(runs) == 1:
        result.update(runs[0])
    else:
        result["runs"] = runs
        result["across_seeds"] = {name: across_seeds([run[name] for run in runs]) for name in runners}
        ratios = [run["up_vs_train_time_to_goal"] for run in runs if "up_vs_train_time_to_goal" in run]
        if ratios:  # only seeds where both runners reached the goal
            result["across_seeds"]["up_vs_train_time_to_goal_median"] = median(ratios)
    print(json.dumps(result))


def run_seed(args: argparse.Namespace, seed: int, settings: list[str], runners: tuple[str, ...]) -> dict:
    """Both runners (or the one of --only) with one seed, each summarized."""
    nasa = [sys.executable, "-m", "nasa.cli"]
    common = ["--task", args.task, "--algo", ALGO, "--preset", "cpu-small", "--device", "cpu", *settings,
              "--seed", str(seed), "--steps", str(args.steps)]
    tag = f"{args.task}-seed{seed}"  # one log per run: tasks and seeds may share --out
    run: dict = {"seed": seed}
    if "train" in runners:
        out = args.out / args.task / ALGO / f"seed{seed}"
        argv = [*nasa, "train", *common, "--out", str(out)]
        run["train"] = launch(argv, out, args.minutes, args.out / f"train-{tag}.log", args.report)
        print(f"nasa train, seed {seed}:", json.dumps(run["train"]), flush=True)
    if "up" in runners:
        out = args.out / "up" / args.task / ALGO / f"seed{seed}"
        # nasa up's default layout, as the README's main command runs it
        argv = [*nasa, "up", *common, "--data", str(out), "--port", str(free_port()),
                "--router-port", str(free_port()), "--logs"]
        minutes = args.up_minutes or args.minutes
        run["up"] = launch(argv, out, minutes, args.out / f"up-{tag}.log", args.report)
        print(f"nasa up, seed {seed}:", json.dumps(run["up"]), flush=True)
    if "train" in run and "up" in run and run["train"]["goal_met"] and run["up"]["goal_met"]:
        run["up_vs_train_time_to_goal"] = round(
            run["up"]["first_goal_launch_s"] / max(run["train"]["first_goal_launch_s"], 1e-9), 3)
    return run


if __name__ == "__main__":
    with stopped_cleanly("python -m bench.learning"):
        main()
