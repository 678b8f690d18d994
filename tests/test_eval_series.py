"""/history's evaluations over a long run: read as eval.csv grows, and bounded in what is served."""

from __future__ import annotations

import os
from pathlib import Path

from fastapi.testclient import TestClient

from services.learner.eval_series import MAX_EVALS, EvalSeries, thin
from services.learner.status_api import make_app
from shared.recorder import Recorder


def test_each_read_parses_only_the_rows_appended_since_the_last(tmp_path):
    recorder = Recorder(tmp_path, eval_episodes=2)
    for i in range(500):
        recorder.eval_row(i * 10, [float(i), float(i + 1)], updates=0)
    series = EvalSeries(tmp_path / "eval.csv")
    assert len(series()) == 500 and series.lines_read == 501  # the header and every row, once
    recorder.eval_row(5000, [7.0, 9.0], updates=0)
    with open(tmp_path / "eval.csv", "a") as f:
        f.write("5010,1")  # a row still being written: left for the next read
    evals = series()
    assert series.lines_read == 502 and evals[-1] == {"step": 5000, "mean": 8.0, "std": 1.0}
    with open(tmp_path / "eval.csv", "a") as f:
        f.write(",0,1,1\n")
    assert series()[-1]["step"] == 5010 and series.lines_read == 503
    assert series() and series.lines_read == 503  # nothing new: nothing parsed


def five_rows(tmp_path: Path) -> tuple[Recorder, EvalSeries]:
    """An eval.csv of steps 0-4 (returns 0-4) and a reader of it."""
    recorder = Recorder(tmp_path, eval_episodes=1)
    for i in range(5):
        recorder.eval_row(i, [float(i)], updates=0)
    return recorder, EvalSeries(tmp_path / "eval.csv")


def test_a_file_cut_back_or_replaced_is_read_again(tmp_path):
    recorder, series = five_rows(tmp_path)
    assert [e["step"] for e in series()] == [0, 1, 2, 3, 4]
    recorder.eval_log.truncate(2)  # a resume drops the rows after its checkpoint
    assert [e["step"] for e in series()] == [0, 1]
    (tmp_path / "new.csv").write_text("step,mean,std,return_0\n9,1,0,1\n")
    os.replace(tmp_path / "new.csv", tmp_path / "eval.csv")
    assert [e["step"] for e in series()] == [9]
    (tmp_path / "eval.csv").unlink()
    assert series() == []


def test_history_serves_a_bounded_evenly_spaced_subset_of_a_long_runs_evaluations(tmp_path):
    recorder = Recorder(tmp_path, eval_episodes=1)
    n = 3 * MAX_EVALS + 7
    for i in range(n):
        recorder.eval_row(i * 1000, [float(i)], updates=0)
    app = make_app(lambda: {}, lambda: [], lambda: [], data=tmp_path, render_every_s=0.0)
    client = TestClient(app)
    steps = [e["step"] for e in client.get("/history").json()["evals"]]
    assert MAX_EVALS // 2 < len(steps) <= MAX_EVALS and steps[0] == 0 and steps[-1] == (n - 1) * 1000
    gaps = [b - a for a, b in zip(steps, steps[1:], strict=False)]
    assert len(set(gaps[:-1])) == 1 and 0 < gaps[-1] <= gaps[0]  # evenly spaced, then the newest
    recorder.eval_row(n * 1000, [1.0], updates=0)
    again = [e["step"] for e in client.get("/history").json()["evals"]]
    assert again[:-1] == steps[:-1] and again[-1] == n * 1000  # the points drawn stay where they were
    assert sum(1 for _ in open(tmp_path / "eval.csv")) == n + 2  # the file keeps every row


def test_thin_keeps_short_series_whole():
    xs = [{"step": i} for i in range(10)]
    assert thin(xs, 10) == xs and thin(xs, 1) == xs[-1:] and thin(xs, 0) == []
    assert thin(xs, 6) == [xs[0], xs[2], xs[4], xs[6], xs[8], xs[9]]
    assert thin(xs, 5) == [xs[0], xs[4], xs[8], xs[9]]


def test_a_file_cut_and_grown_past_its_old_size_between_reads_is_read_again(tmp_path):
    recorder = Recorder(tmp_path, eval_episodes=1)
    for i in range(5):
        recorder.eval_row(i, [float(i)], updates=0)
    series = EvalSeries(tmp_path / "eval.csv")
    assert len(series()) == 5
    recorder.eval_log.truncate(2)
    for i in range(100, 110):
        recorder.eval_row(i, [float(i)], updates=0)
    assert [e["step"] for e in series()] == [0, 1, *range(100, 110)]


def test_a_file_cut_and_grown_back_to_its_old_size_between_reads_is_read_again(tmp_path):
    # A resume drops rows after its checkpoint and its evaluations write them again: rows of the
    # same length leave the file at the size last read, with other returns in it.
    recorder, series = five_rows(tmp_path)
    assert [e["mean"] for e in series()] == [0.0, 1.0, 2.0, 3.0, 4.0]
    size = os.path.getsize(tmp_path / "eval.csv")
    recorder.eval_log.truncate(3)
    for i in (3, 4):
        recorder.eval_row(i, [float(i + 5)], updates=0)
    assert os.path.getsize(tmp_path / "eval.csv") == size
    assert [e["mean"] for e in series()] == [0.0, 1.0, 2.0, 8.0, 9.0]
