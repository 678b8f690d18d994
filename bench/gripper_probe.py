"""Does a gripper run's encoder see the valve and the target? A linear probe of its latent.

A pixel agent that does not learn the stand-in either cannot see what the reward depends on (the
valve's angle and the target's, from a small image) or sees it and fails to act on it. This tells
the two apart: it plays random actions on a fresh stand-in (a seed neither training nor
evaluation used), encodes every frame stack with the run's last checkpoint, fits a ridge
regression from the latent to (cos, sin) of each angle on the first 70% of the episodes and
reports, on the rest, R^2 and the mean error of the angle it predicts, in degrees. The same for an
encoder as the run built it before training (its seed, no updates) says what comes for free.

What to read it against: an encoder that holds nothing of an angle scores R^2 about 0 and a mean
error of about 90 degrees (a uniform angle guessed at its mean); one that holds it exactly, R^2 1
and 0 degrees.

    python -m bench.gripper_probe RUN [--steps 5000]

RUN is a `nasa train` run folder (config.json, checkpoint.pt) of `gripper-valve` or
`gripper-valve_reset`. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from shared import checkpoint, envs
from shared.agents import make_agent
from shared.gripper import TASK_NAMES
from shared.gripper.sim import EPISODE_STEPS
from shared.run_config import read_config

PROBE_SEED = 7_000_000  # not a training seed (0, 1, ...) nor an evaluation one (seed + 1,000,000)
TRAIN_FRACTION = 0.7
RIDGE = 1e-2  # times the number of rows: a light pull toward zero on standardised features
ENCODE_BATCH = 256


def play(env: envs.PixelEnv, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`steps` frame stacks under uniform random actions, and the (valve, target) angles of each."""
    sim, rng = env.pixels, np.random.default_rng(seed)
    stacks, angles = [], []
    step = env.reset()
    for _ in range(steps):
        if step.last:
            step = env.reset()
        stacks.append(step.obs.copy())
        angles.append((sim.valve_angle, sim.target_angle))
        step = env.step(rng.uniform(-1.0, 1.0, env.action_dim).astype(np.float32))
    return np.stack(stacks), np.array(angles)


def encode(encoder: torch.nn.Module, stacks: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return torch.cat([encoder(torch.as_tensor(stacks[i:i + ENCODE_BATCH]))
                          for i in range(0, len(stacks), ENCODE_BATCH)]).numpy()


def probe(features: np.ndarray, angles: np.ndarray, n_train: int) -> dict[str, float]:
    """Ridge from `features` to (cos, sin) of each column of `angles`, fitted on the first `n_train`
    rows; per angle, the R^2 of its (cos, sin) and the mean error in degrees on the other rows."""
    mean, std = features[:n_train].mean(0), features[:n_train].std(0) + 1e-6
    x = np.hstack([(features - mean) / std, np.ones((len(features), 1))])
    y = np.concatenate([np.cos(angles), np.sin(angles)], axis=1)  # cos of each, then sin of each
    a = x[:n_train]
    w = np.linalg.solve(a.T @ a + RIDGE * n_train * np.eye(a.shape[1]), a.T @ y[:n_train])
    predicted, truth = x[n_train:] @ w, y[n_train:]
    r2 = 1.0 - ((predicted - truth) ** 2).sum(0) / ((truth - truth.mean(0)) ** 2).sum(0)
    k = angles.shape[1]
    error = np.arctan2(predicted[:, k:], predicted[:, :k]) - angles[n_train:]
    error = np.abs((error + math.pi) % (2 * math.pi) - math.pi)
    return {"r2": [round(float((r2[i] + r2[k + i]) / 2), 3) for i in range(k)],
            "error_deg": [round(float(np.degrees(error[:, i].mean())), 1) for i in range(k)]}


def run_probe(run: Path, steps: int) -> dict:
    config = read_config(run / "config.json")
    if config.env.task not in TASK_NAMES:
        raise ValueError(f"{run} is a {config.env.task} run; the probe reads the gripper's angles "
                         f"({', '.join(TASK_NAMES)})")
    if not (run / "checkpoint.pt").is_file():
        raise ValueError(f"{run} has no checkpoint.pt: the run has not reached its first checkpoint")
    state = checkpoint.load(run / "checkpoint.pt")
    env = envs.from_config(config.env, PROBE_SEED)
    spec, device = env.spec, torch.device("cpu")
    stacks, angles = play(env, steps, PROBE_SEED)
    n_train = int(steps * TRAIN_FRACTION) // EPISODE_STEPS * EPISODE_STEPS  # whole episodes each side
    torch.manual_seed(config.seed)  # the encoder as the run built it
    untrained = make_agent(config.algo, spec.obs_shape, spec.action_dim, config.agent, device)
    trained = make_agent(config.algo, spec.obs_shape, spec.action_dim, config.agent, device)
    trained.load_state_dict(state["agent"])
    result = {"run": str(run), "task": config.env.task, "algo": config.algo,
              "image_size": config.env.image_size, "trained_env_steps": state["env_steps"],
              "probe_steps": steps, "probe_train_rows": n_train}
    for name, agent in (("untrained", untrained), ("trained", trained)):
        scores = probe(encode(agent.encoder, stacks), angles, n_train)
        result[name] = {"valve_r2": scores["r2"][0], "target_r2": scores["r2"][1],
                        "valve_error_deg": scores["error_deg"][0], "target_error_deg": scores["error_deg"][1]}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run", type=Path, help="a gripper run folder of nasa train")
    parser.add_argument("--steps", type=int, default=5_000, help="frame stacks to probe with")
    args = parser.parse_args()
    if args.steps < 4 * EPISODE_STEPS:
        parser.error(f"--steps must be >= {4 * EPISODE_STEPS} (whole episodes on each side of the split)")
    if not (args.run / "config.json").is_file():
        parser.error(f"{args.run} has no config.json: not a nasa train run folder")
    try:
        result = run_probe(args.run, args.steps)
    except ValueError as err:  # a task without the angles, or a checkpoint this version cannot read
        print(f"gripper_probe: {err}", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
