"""eval.csv: what one evaluation's row holds, and an old run's file read and continued as it is."""

from __future__ import annotations

from pathlib import Path

import pytest

from nasa.plot import find_runs
from shared.recorder import Recorder
from shared.runlog import RunLogError, read_rows


def test_a_row_holds_the_weights_update_count_and_the_spread_of_the_returns(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path, 3)
    row = recorder.eval_row(1000, [10.0, 40.0, 100.0], updates=4995)
    (written,) = read_rows(tmp_path / "eval.csv")
    assert list(written) == ["step", "updates", "mean", "std", "min", "max",
                             "return_0", "return_1", "return_2"]
    assert written["updates"] == "4995" and written["min"] == "10" and written["max"] == "100"
    assert row["mean"] == pytest.approx(50.0) and row["std"] == pytest.approx(37.416573867739416)
    assert recorder.last_eval() == {"step": 1000, "mean": 50.0, "std": pytest.approx(37.4166, rel=1e-5)}


OLD = b"step,mean,std,return_0,return_1\r\n0,12.5,0.5,12,13\r\n1000,30,1,29,31\r\n"


def test_an_old_runs_eval_csv_is_continued_under_its_own_header_and_still_plots(tmp_path: Path) -> None:
    """A run written before the updates, min and max columns: a resume appends rows under its
    header (without them), and nasa plot reads it."""
    run = tmp_path / "cartpole-balance" / "nasa_td3" / "seed0"
    run.mkdir(parents=True)
    (run / "eval.csv").write_bytes(OLD)
    recorder = Recorder(run, 2)
    assert recorder.last_eval() == {"step": 1000, "mean": 30.0, "std": 1.0}
    recorder.eval_row(2000, [300.0, 310.0], updates=1000)
    rows = read_rows(run / "eval.csv")
    assert list(rows[-1]) == ["step", "mean", "std", "return_0", "return_1"]
    assert rows[-1] == {"step": "2000", "mean": "305", "std": "5", "return_0": "300", "return_1": "310"}
    (curve,) = find_runs(tmp_path)
    assert curve.steps.tolist() == [0, 1000, 2000] and curve.means.tolist() == [12.5, 30.0, 305.0]


def test_an_old_header_of_other_settings_is_still_refused(tmp_path: Path) -> None:
    (tmp_path / "eval.csv").write_bytes(OLD)  # two episodes; this run evaluates three
    with pytest.raises(RunLogError, match="does not start with the header"):
        Recorder(tmp_path, 3)
    assert (tmp_path / "eval.csv").read_bytes() == OLD
