"""Render cost and pixel difference of the render qualities on the six paper tasks.

`paper` renders the suite's scene as is (2048 shadow map, 4x multisampling);
`fast` uses a 512 shadow map and no multisampling; `plain` is `fast` without
shadows or floor reflections (shared/gl.py). The envs are stepped with the same
seed and actions, so they show the same states; each quality's frames are
compared with `paper`'s.

    python -m bench.render [--frames 200] [--tasks T ...]
    python -m bench.render --gl-threads [--frames 200] [--rounds 3] [--tasks T ...]

`--gl-threads` instead compares Mesa's software rasterizer drawing in the
calling thread (LP_NUM_THREADS=0, the project's default: shared/gl.py) with
its own default of a thread per core, `fast` quality: alternating processes,
each stepping every paper task, wall-clock and CPU (all threads) per env step,
and whether the frames are the same. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time

import numpy as np

from bench.args import task_name
from shared import envs, gl

QUALITIES = gl.RENDER_QUALITIES  # paper first: the others are compared with it


def measure(task: str, frames: int) -> dict:
    """Per quality: env steps/s and CPU ms per step (physics and render, after a few untimed
    frames that make the GL context), and how far its frames are from `paper`'s."""
    made = {q: envs.make(task, seed=0, render_quality=q) for q in QUALITIES}
    actions = np.random.default_rng(0).uniform(-1, 1, (frames, made["paper"].action_dim))
    result: dict = {}
    stacks: dict[str, np.ndarray] = {}
    for name, env in made.items():
        for _ in range(3):
            env.reset()
        ts = env.reset()
        got = [ts.frame]
        start, cpu = time.perf_counter(), time.process_time()
        for action in actions:
            ts = env.step(action)
            got.append(ts.frame)
            if ts.last:
                ts = env.reset()
        result[f"{name}_steps_per_s"] = round(frames / (time.perf_counter() - start), 1)
        result[f"{name}_cpu_ms_per_step"] = round(1e3 * (time.process_time() - cpu) / frames, 2)
        stacks[name] = np.stack(got).astype(np.int16)
    for name in QUALITIES[1:]:
        diff = np.abs(stacks["paper"] - stacks[name])
        result[f"{name}_mean_abs_diff"] = round(float(diff.mean()), 3)  # on the 0..255 scale
        result[f"{name}_pixels_differing_pct"] = round(float((diff.max(axis=1) > 8).mean() * 100), 2)
    return result


def step_cost(task: str, frames: int) -> dict:
    """Wall-clock and CPU milliseconds per `fast` env step in this process, and the frames' digest."""
    env = envs.make(task, seed=0, render_quality="fast")
    actions = np.random.default_rng(0).uniform(-1, 1, (frames, env.action_dim))
    env.reset()
    for action in actions[: frames // 10]:  # the GL context and its shaders are made on the first frames
        env.step(action)
    ts, digest = env.reset(), hashlib.sha256()
    wall, cpu = time.perf_counter(), time.process_time()
    for action in actions:
        ts = env.step(action)
        digest.update(ts.frame.tobytes())
        if ts.last:
            ts = env.reset()
    return {"wall_ms": 1e3 * (time.perf_counter() - wall) / frames,
            "cpu_ms": 1e3 * (time.process_time() - cpu) / frames, "digest": digest.hexdigest()}


def gl_threads(frames: int, rounds: int, tasks: list[str]) -> dict:
    """Each paper task stepped with LP_NUM_THREADS=0 and with a rasterizer thread per core, in
    alternating processes; medians over the rounds."""
    settings = {"caller_thread": "0", "thread_per_core": str(os.cpu_count() or 1)}
    runs: dict[str, list[dict]] = {name: [] for name in settings}
    for r in range(rounds):
        for name in (list(settings) if r % 2 == 0 else list(settings)[::-1]):
            out = subprocess.run([sys.executable, "-m", "bench.render", "--child", "--frames", str(frames),
                                  "--tasks", *tasks],
                                 env={**os.environ, "LP_NUM_THREADS": settings[name]},
                                 capture_output=True, text=True, check=True)
            runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    result: dict = {}
    for task in tasks:
        row = {}
        for name in settings:
            row[f"{name}_wall_ms"] = round(float(np.median([run[task]["wall_ms"] for run in runs[name]])), 2)
            row[f"{name}_cpu_ms"] = round(float(np.median([run[task]["cpu_ms"] for run in runs[name]])), 2)
        row["same_frames"] = len({run[task]["digest"] for name in settings for run in runs[name]}) == 1
        result[task] = row
        one, per_core = (f"{row[f'{n}_wall_ms']:6.2f} ms ({row[f'{n}_cpu_ms']:.2f} CPU)" for n in settings)
        print(f"{task:18s} caller thread {one}  thread per core {per_core}  same frames {row['same_frames']}",
              flush=True)
    return {"frames": frames, "rounds": rounds, "cores": os.cpu_count(), "tasks": result}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--gl-threads", action="store_true", help="compare the rasterizer's threads")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--tasks", nargs="+", type=task_name, default=list(envs.PAPER_TASKS))
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps({task: step_cost(task, args.frames) for task in args.tasks}))
        return
    if args.gl_threads:
        print(json.dumps(gl_threads(args.frames, args.rounds, args.tasks)))
        return
    results = {}
    for task in args.tasks:
        results[task] = r = measure(task, args.frames)
        rates = "  ".join(f"{q} {r[f'{q}_steps_per_s']:6.1f}/s ({r[f'{q}_cpu_ms_per_step']:.2f} ms CPU)"
                          for q in QUALITIES)
        diffs = "  ".join(f"{q} |diff| {r[f'{q}_mean_abs_diff']:.2f}/255, "
                          f">8 apart {r[f'{q}_pixels_differing_pct']:.1f}%" for q in QUALITIES[1:])
        print(f"{task:18s} {rates}  vs paper: {diffs}", flush=True)
    print(json.dumps({"frames": args.frames, "image_size": 84, "tasks": results}))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.render"):
        main()
