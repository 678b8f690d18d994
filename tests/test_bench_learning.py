"""bench.learning's command line: its own flags, and the settings it passes to both runs."""

import json
import sys

import pytest

from bench.learning import launch, load_times, run_bounded, split_settings, summarize


def test_settings_after_a_double_dash_go_to_the_runs():
    own, settings = split_settings(["--task", "gripper-valve", "--", "--action-repeat", "1"])
    assert own == ["--task", "gripper-valve"] and settings == ["--action-repeat", "1"]
    assert split_settings(["--only", "train"]) == (["--only", "train"], [])
    assert split_settings(["--"]) == ([], [])


def test_evaluation_rows_are_timed_from_the_launch_and_the_bound_stops_the_run(tmp_path):
    # A stand-in run: writes two evaluation rows a while apart, half a third one, then hangs.
    eval_csv = tmp_path / "run" / "eval.csv"
    script = (
        "import pathlib, sys, time\n"
        f"p = pathlib.Path({str(eval_csv)!r}); p.parent.mkdir(parents=True)\n"
        "f = open(p, 'w', buffering=1); f.write('step,mean\\n0,0\\n'); time.sleep(1.5)\n"
        "f.write('1000,750\\n'); f.write('2000,12'); f.flush(); time.sleep(60)\n"
    )
    wall, seen = run_bounded([sys.executable, "-c", script], 4 / 60, tmp_path / "run.log",
                             eval_csv, poll_s=0.1)
    assert 4 <= wall < 30  # stopped at the bound, not after the run's own 60 s
    assert set(seen) == {0, 1000}  # the half-written row is not a row
    assert 1.4 <= seen[1000] - seen[0] <= 3.5
    summary = summarize(eval_csv.parent, wall, 4.0, seen)
    assert summary["untrained"] == 0 and summary["best_within_bound"] == 750
    assert summary["first_goal_step"] == 1000 and summary["first_goal_launch_s"] == seen[1000]
    # Past the bound, a row does not count.
    late = summarize(eval_csv.parent, wall, seen[1000] - 0.05, seen)
    assert not late["goal_met"] and late["best_within_bound"] == 0


def test_saved_launch_times_are_read_back_and_a_bad_file_is_a_clear_error(tmp_path):
    log = tmp_path / "train-t-seed0.log"
    # The times file cannot be written (a folder stands in its way, as a full disk would refuse it):
    # the run is still summarized.
    log.with_suffix(".evals.json").mkdir()
    summary = launch([sys.executable, "-c", "pass"], tmp_path / "run", 1.0, log, report_only=False)
    assert summary["untrained"] is None and summary["wall_s"] < 30
    log.with_suffix(".evals.json").rmdir()
    assert load_times(log.with_suffix(".evals.json")) == (0.0, {})  # nothing saved: no times
    times = log.with_suffix(".evals.json")
    times.write_text(json.dumps({"wall_s": 12.5, "seen": {"0": 3.0, "1000": 9.5}}))
    assert load_times(times) == (12.5, {0: 3.0, 1000: 9.5})
    for bad in ("{not json", json.dumps({"wall_s": 1.0}), json.dumps({"wall_s": 1, "seen": {"x": 1}}), "[]"):
        times.write_text(bad)
        with pytest.raises(SystemExit, match="not a file of launch times"):
            load_times(times)
