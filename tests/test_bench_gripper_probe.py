"""bench.gripper_probe: a linear probe of a gripper run's encoder for the valve's and target's angles."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from bench.gripper_probe import probe
from nasa.train import Trainer
from shared.config import default_config


def angles(n=2000, seed=0):
    return np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, (n, 2))


def test_features_that_hold_the_angles_are_read_back_and_noise_is_not():
    a = angles()
    noise = np.random.default_rng(1).normal(size=(len(a), 8))
    holding = np.hstack([np.cos(a), np.sin(a), 0.01 * noise])
    held = probe(holding, a, 1400)
    assert min(held["r2"]) > 0.99 and max(held["error_deg"]) < 2.0
    blind = probe(noise, a, 1400)
    assert max(blind["r2"]) < 0.05 and min(blind["error_deg"]) > 60.0
    # one angle held and the other not: the probe tells them apart
    half = probe(np.hstack([np.cos(a[:, :1]), np.sin(a[:, :1]), noise]), a, 1400)
    assert half["r2"][0] > 0.99 and half["r2"][1] < 0.05


def run(*args):
    return subprocess.run([sys.executable, "-m", "bench.gripper_probe", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def tiny_run(path, task="gripper-valve"):
    config = default_config("nasa_td3", "cpu-small", task)
    config.env.task = task
    config.steps, config.warmup_steps, config.batch_size = 100, 20, 8
    config.eval_every, config.eval_episodes, config.replay_capacity = 100, 1, 1000
    config.checkpoint_every, config.device = 1, "cpu"
    config.env.image_size = 32
    config.agent.latent_dim, config.agent.hidden_dim = 16, 32
    config.agent.ensemble_hidden_dim, config.agent.num_filters = 16, 8
    Trainer.create(config, path).run()
    return path


def test_a_real_run_is_probed_end_to_end(tmp_path):
    done = run(tiny_run(tmp_path / "run"), "--steps", 200)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["task"] == "gripper-valve" and result["trained_env_steps"] == 100  # two whole episodes
    assert result["probe_train_rows"] == 100  # whole episodes on the fitting side
    for name in ("untrained", "trained"):
        assert set(result[name]) == {"valve_r2", "target_r2", "valve_error_deg", "target_error_deg"}
        assert all(0.0 <= result[name][k] <= 180.0 for k in ("valve_error_deg", "target_error_deg"))


BAD = ["no folder", "too few steps", "a suite run", "no checkpoint yet", "a broken checkpoint"]


@pytest.mark.parametrize("case", BAD)
def test_bad_input_is_one_clear_error(tmp_path, case):
    folder = tmp_path / "run"
    if case == "a suite run":
        tiny_run(folder, "cartpole-balance")
    elif case == "no checkpoint yet":
        tiny_run(folder)
        (folder / "checkpoint.pt").unlink()
    elif case == "a broken checkpoint":
        tiny_run(folder)
        (folder / "checkpoint.pt").write_bytes(b"not a checkpoint")
    done = run(folder, "--steps", 10 if case == "too few steps" else 200)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    expected = {"no folder": "no config.json", "too few steps": "--steps must be",
                "a suite run": "a cartpole-balance run",
                "no checkpoint yet": "no checkpoint.pt",
                "a broken checkpoint": "not a readable checkpoint"}[case]
    assert expected in done.stderr
