"""Render cost and pixel difference of the two render qualities on the six paper tasks.

`paper` renders the suite's scene as is (2048 shadow map, 4x multisampling);
`fast` uses a 512 shadow map and no multisampling. Both envs are stepped with
the same seed and actions, so they show the same states.

    python -m bench.render [--frames 200]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from shared import envs


def measure(task: str, frames: int) -> dict:
    paper = envs.make(task, seed=0, render_quality="paper")
    fast = envs.make(task, seed=0, render_quality="fast")
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (frames, paper.action_dim))
    result: dict = {}
    stacks: dict[str, list[np.ndarray]] = {}
    for name, env in (("paper", paper), ("fast", fast)):
        ts = env.reset()
        got = [ts.frame]
        start = time.perf_counter()
        for action in actions:
            ts = env.step(action)
            got.append(ts.frame)
            if ts.last:
                ts = env.reset()
        result[f"{name}_steps_per_s"] = round(frames / (time.perf_counter() - start), 1)
        stacks[name] = got
    a = np.stack(stacks["paper"]).astype(np.int16)
    b = np.stack(stacks["fast"]).astype(np.int16)
    diff = np.abs(a - b)
    result["mean_abs_diff"] = round(float(diff.mean()), 3)  # on the 0..255 scale
    result["pixels_differing_pct"] = round(float((diff.max(axis=1) > 8).mean() * 100), 2)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=200)
    args = parser.parse_args()
    results = {}
    for task in envs.PAPER_TASKS:
        results[task] = measure(task, args.frames)
        r = results[task]
        print(
            f"{task:18s} paper {r['paper_steps_per_s']:6.1f}/s  fast {r['fast_steps_per_s']:6.1f}/s  "
            f"mean |diff| {r['mean_abs_diff']:.2f}/255  pixels >8 apart {r['pixels_differing_pct']:.1f}%"
        )
    print(json.dumps({"frames": args.frames, "image_size": 84, "tasks": results}))


if __name__ == "__main__":
    main()
