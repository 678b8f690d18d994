"""Does it learn? The cpu-small preset on cartpole-balance, bounded by wall-clock time.

Runs `nasa train` (single process) and then `nasa up --actors 2` (the
distributed system) with the cpu-small preset, each for at most --minutes of
wall-clock time, reads each run's eval.csv and prints the evaluation returns
over steps. Goal on the 2-core CPU: a mean evaluation return of at least 700
within 30 minutes, against about 0-200 (here ~300, see step 0) for the
untrained policy.

    python -m bench.learning [--minutes 30] [--up-minutes M] [--out bench-results/learning] [--only train|up]

The last line is one JSON object. `nasa plot <out>` draws the curves.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from nasa.up import free_port
from shared.runlog import read_rows

TASK = "cartpole-balance"
ALGO = "nasa_td3"
GOAL = 700.0


def run_bounded(argv: list[str], minutes: float, log: Path) -> float:
    """Run a command until it ends or the time is up (then Ctrl-C it); returns the wall-clock used."""
    start = time.monotonic()
    with open(log, "w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            proc.wait(timeout=minutes * 60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGINT)  # a clean stop, as a user's Ctrl-C
            try:
                proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return time.monotonic() - start


def summarize(eval_csv: Path, wall_s: float) -> dict:
    rows = read_rows(eval_csv) if eval_csv.exists() else []
    curve = [[int(r["step"]), round(float(r["mean"]), 1)] for r in rows]
    means = [m for _, m in curve]
    reached = next((s for s, m in curve if m >= GOAL), None)
    return {
        "evals": curve,
        "wall_s": round(wall_s, 1),
        "untrained": means[0] if means else None,
        "final": means[-1] if means else None,
        "best": max(means) if means else None,
        "first_step_at_goal": reached,
        "goal_met": reached is not None,
    }


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
    args = parser.parse_args()
    result: dict = {"task": TASK, "algo": ALGO, "preset": "cpu-small", "minutes": args.minutes, "goal": GOAL}
    nasa = [sys.executable, "-m", "nasa.cli"]
    common = ["--task", TASK, "--algo", ALGO, "--preset", "cpu-small", "--device", "cpu"]
    if args.only in (None, "train"):
        out = args.out / TASK / ALGO / f"seed{args.seed}"
        shutil.rmtree(out, ignore_errors=True)
        out.parent.mkdir(parents=True, exist_ok=True)
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
        print("running:", " ".join(argv[2:]), flush=True)
        wall = run_bounded(argv, args.minutes, args.out / "train.log")
        result["train"] = summarize(out / "eval.csv", wall)
        print("nasa train:", json.dumps(result["train"]), flush=True)
    if args.only in (None, "up"):
        out = args.out / "up" / f"{TASK}-{ALGO}-2actors"
        shutil.rmtree(out, ignore_errors=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        argv = [
            *nasa, "up", "--task", TASK, "--algo", ALGO, "--preset", "cpu-small", "--device", "cpu",
            "--actors", "2", "--steps", str(args.steps), "--data", str(out), "--seed", str(args.seed),
            "--port", str(free_port()), "--router-port", str(free_port()), "--logs",
        ]  # fmt: skip
        print("running:", " ".join(argv[2:]), flush=True)
        wall = run_bounded(argv, args.up_minutes or args.minutes, args.out / "up.log")
        result["up"] = summarize(out / "eval.csv", wall)
        print("nasa up:", json.dumps(result["up"]), flush=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
