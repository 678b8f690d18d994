"""Does it learn? The cpu-small preset on the headline task, bounded by wall-clock time.

Runs `nasa train` (single process) and then `nasa up` (the distributed system,
in the layout it chooses for this machine, as the README's main command) with
the cpu-small preset, each for at most --minutes of wall-clock time, reads each
run's eval.csv and reports the untrained policy's return (the evaluation at
step 0), the best and the last return, and the wall-clock time to a mean
evaluation return of 700. The headline task, ball_in_cup-catch, has a sparse
reward: the untrained policy scores near 0 there. Goals on a 2-core CPU:
`nasa up` reaches 700 within 30 minutes, in at most 1.1x the time `nasa train`
takes (`up_vs_train_time_to_goal`).

    python -m bench.learning [--task T] [--minutes 30] [--up-minutes M] [--out bench-results/learning]
                             [--only train|up] [--report] [-- SETTINGS]

SETTINGS are `nasa train` flags passed to both runs after the preset's, for a documented
per-task variant (the gripper's 50-step episodes take `-- --action-repeat 1`).

The last line is one JSON object. `nasa plot <out>` draws the curves.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from nasa.layout import usable_cores
from nasa.up import free_port
from shared.runlog import eval_walls, read_rows

TASK = "ball_in_cup-catch"
ALGO = "nasa_td3"
GOAL = 700.0


def run_bounded(argv: list[str], minutes: float, log: Path) -> float:
    """Run a command until it ends or the time is up; returns the wall-clock used.

    At the bound it gets SIGINT (a user's Ctrl-C), then SIGTERM: a process
    started in the background by a non-interactive shell ignores SIGINT.
    """
    start = time.monotonic()
    with open(log, "w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            proc.wait(timeout=minutes * 60)
        except subprocess.TimeoutExpired:
            for sig, grace in ((signal.SIGINT, 20), (signal.SIGTERM, 60), (signal.SIGKILL, None)):
                os.killpg(proc.pid, sig)
                try:
                    proc.wait(timeout=grace)
                    break
                except subprocess.TimeoutExpired:
                    continue
    return time.monotonic() - start


def summarize(run: Path, wall_s: float, bound_s: float) -> dict:
    """Evaluation returns over steps, each with the run's wall-clock when it was reached.

    The wall-clock of an evaluation step is read from train.csv (the first
    episode that ends at or after it); the goal counts only within the bound.
    """
    rows = read_rows(run / "eval.csv") if (run / "eval.csv").exists() else []
    walls = eval_walls(run, [int(r["step"]) for r in rows])

    def wall_at(step: int) -> float | None:
        return round(walls[step], 1) if step in walls else None

    curve = [[int(r["step"]), round(float(r["mean"]), 1), wall_at(int(r["step"]))] for r in rows]
    within = [(s, m, w) for s, m, w in curve if w is not None and w <= bound_s]
    reached = next(((s, w) for s, m, w in within if m >= GOAL), None)
    return {
        "evals_step_mean_wall_s": curve,
        "wall_s": round(wall_s, 1),
        "untrained": curve[0][1] if curve else None,
        "best_within_bound": max((m for _, m, _ in within), default=None),
        "final_within_bound": within[-1][1] if within else None,
        "first_goal_step": reached[0] if reached else None,
        "first_goal_wall_s": reached[1] if reached else None,
        "goal_met": reached is not None,
    }


def launch(argv: list[str], out: Path, minutes: float, log: Path, report_only: bool) -> float:
    """Start a fresh run in `out` (or, with --report, only read the wall-clock of the last one)."""
    if report_only:
        episodes = read_rows(out / "train.csv")
        return float(episodes[-1]["wall_s"]) if episodes else 0.0
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    print("running:", " ".join(argv[2:]), flush=True)
    return run_bounded(argv, minutes, log)


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
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--task", default=TASK, help="the task (default: the headline task)")
    parser.add_argument("--report", action="store_true", help="only summarize the runs already in --out")
    own, settings = split_settings(sys.argv[1:])
    args = parser.parse_args(own)
    result: dict = {"task": args.task, "algo": ALGO, "preset": "cpu-small", "minutes": args.minutes,
                    "goal": GOAL, "cores": usable_cores(), "machine": platform.node(), "settings": settings}
    nasa = [sys.executable, "-m", "nasa.cli"]
    common = ["--task", args.task, "--algo", ALGO, "--preset", "cpu-small", "--device", "cpu", *settings]
    if args.only in (None, "train"):
        out = args.out / args.task / ALGO / f"seed{args.seed}"
        argv = [
            *nasa,
            "train",
            *common,
            "--seed",
            str(args.seed),
            "--steps",
            str(args.steps),
            "--out",
            str(out),
        ]
        wall = launch(argv, out, args.minutes, args.out / "train.log", args.report)
        result["train"] = summarize(out, wall, args.minutes * 60)
        print("nasa train:", json.dumps(result["train"]), flush=True)
    if args.only in (None, "up"):
        out = args.out / "up" / args.task / ALGO / f"seed{args.seed}"
        # nasa up's default layout, as the README's main command runs it
        argv = [
            *nasa, "up", *common, "--steps", str(args.steps), "--data", str(out), "--seed", str(args.seed),
            "--port", str(free_port()), "--router-port", str(free_port()), "--logs",
        ]  # fmt: skip
        minutes = args.up_minutes or args.minutes
        wall = launch(argv, out, minutes, args.out / "up.log", args.report)
        result["up"] = summarize(out, wall, minutes * 60)
        print("nasa up:", json.dumps(result["up"]), flush=True)
    if "train" in result and "up" in result and result["train"]["goal_met"] and result["up"]["goal_met"]:
        result["up_vs_train_time_to_goal"] = round(
            result["up"]["first_goal_wall_s"] / max(result["train"]["first_goal_wall_s"], 1e-9), 3)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
