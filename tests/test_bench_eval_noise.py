"""bench.eval_noise: what a smaller evaluation would have read from a run evaluated with many
episodes, on an eval.csv written by the runners' own recorder."""

import json
import subprocess
import sys

import numpy as np
import pytest

from bench.eval_noise import analyse, chance_of_goal, first_goal_distribution, returns_by_step
from shared.recorder import Recorder


def write_run(tmp_path, evaluations: dict[int, list[float]]):
    recorder = Recorder(tmp_path, max(len(r) for r in evaluations.values()))
    for step, returns in evaluations.items():
        recorder.eval_row(step, returns, updates=step)
    return tmp_path / "eval.csv"


def test_the_chance_of_a_small_evaluation_reading_the_goal():
    rng = np.random.default_rng(1)
    half = np.array([0.0, 1000.0] * 25)  # catches in half the episodes
    # 700 needs 4 or 5 catches of 5: (5 + 1) / 32.
    assert chance_of_goal(half, 5, 700.0, 200_000, rng) == pytest.approx(6 / 32, abs=0.005)
    assert chance_of_goal(np.full(50, 1000.0), 5, 700.0, 1000, rng) == 1.0
    assert chance_of_goal(np.zeros(50), 5, 700.0, 1000, rng) == 0.0
    # With many episodes a mean of 500 almost never reads 700.
    assert chance_of_goal(half, 200, 700.0, 20_000, rng) < 0.001


def test_the_first_evaluation_to_read_the_goal():
    first, never = first_goal_distribution([0.0, 0.5, 0.5, 1.0])
    assert first == [0.0, 0.5, 0.25, 0.25] and never == 0.0
    first, never = first_goal_distribution([0.1, 0.1])
    assert first == pytest.approx([0.1, 0.09]) and never == pytest.approx(0.81)


def test_a_run_folder_is_read_off(tmp_path):
    csv = write_run(tmp_path, {0: [0.0] * 50, 1000: [0.0, 1000.0] * 25, 2000: [1000.0] * 50})
    rows = returns_by_step(csv)
    assert [s for s, _ in rows] == [0, 1000, 2000] and all(len(r) == 50 for _, r in rows)
    result = analyse(rows, 5, 700.0, 50_000)
    chances = [r["chance_of_goal"] for r in result["per_step"]]
    assert chances[0] == 0.0 and chances[1] == pytest.approx(6 / 32, abs=0.01) and chances[2] == 1.0
    assert result["first_step_mean_at_goal"] == 2000  # the mean of 50 crosses only there
    assert result["chance_goal_read_by_last_step"] == 1.0
    assert result["median_first_goal_step"] == 2000
    assert result["per_step"][1]["mean"] == 500.0 and result["per_step"][1]["ci95"] > 100


def test_the_command_prints_one_json_line_last_and_refuses_a_folder_without_evaluations(tmp_path):
    write_run(tmp_path / "run", {0: [0.0, 990.0, 0.0], 1000: [990.0, 990.0, 0.0]})
    done = subprocess.run([sys.executable, "-m", "bench.eval_noise", str(tmp_path / "run"),
                           "--episodes", "2", "--resamples", "1000"],
                          capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["episodes_per_evaluation"] == 2 and len(result["per_step"]) == 2
    (tmp_path / "empty").mkdir()
    refused = subprocess.run([sys.executable, "-m", "bench.eval_noise", str(tmp_path / "empty")],
                             capture_output=True, text=True)
    assert refused.returncode == 2 and "eval.csv" in refused.stderr


def test_a_mean_just_under_the_goal_is_not_read_as_the_goal():
    # 699.96, shown rounded as 700.0, is under 700.
    rows = [(0, np.array([699.92, 700.0])), (1000, np.array([700.0, 700.0]))]
    result = analyse(rows, 2, 700.0, 1000)
    assert result["per_step"][0]["mean"] == 700.0  # as printed
    assert result["first_step_mean_at_goal"] == 1000
