"""bench.learner refuses bad input in one line with exit 2, before it renders or starts anything."""

from __future__ import annotations

import pytest

from bench import learner


def refused(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    with pytest.raises(SystemExit) as exit_:
        learner.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_a_folder_that_is_not_the_reference_checkout_is_one_line(tmp_path, capsys):
    (tmp_path / "networks").mkdir()  # half a checkout: no nasa_td3.py
    for folder in (tmp_path / "missing", tmp_path, tmp_path / "networks"):
        err = refused(["--reference", str(folder)], capsys)
        assert err.count("\n") == 1 and "is not a checkout of UoA-CARES/NaSA_TD3" in err


def test_an_unknown_device_is_one_line(capsys):
    err = refused(["--device", "tpu"], capsys)
    assert err.count("\n") == 1 and "unknown device 'tpu'" in err


@pytest.mark.parametrize("flag", ["--batch", "--rounds", "--updates", "--score-repeats", "--peak-seconds"])
def test_counts_and_times_must_be_above_zero(flag, capsys):
    assert f"argument {flag}: must be above 0" in refused([flag, "0"], capsys)


def test_an_unknown_algorithm_is_refused_before_any_worker_runs(capsys):
    assert "argument --algo: invalid choice: 'td4'" in refused(["--algo", "td4"], capsys)


def test_the_reference_scores_as_many_timed_passes_as_the_project(monkeypatch, cpu):
    import numpy as np

    from bench import reference

    scored = []
    monkeypatch.setattr(reference, "make", lambda *a, **k: object())
    monkeypatch.setattr(reference, "update", lambda agent, data: None)
    monkeypatch.setattr(reference, "score_one", lambda agent, *t: scored.append(1) or 0.0)
    data = {"stacks": np.zeros((33, 9, 8, 8), np.uint8), "action": np.zeros((32, 6), np.float32)}
    learner.reference_worker(data, cpu, updates=2, directory=None, count=False, score_repeats=3)
    assert len(scored) == learner.SINGLES * (1 + 3)  # one untimed pass, then the project's repeats


def test_the_bf16_peak_is_timed_only_for_a_bf16_variant(monkeypatch, cpu, tmp_path):
    """A CPU without bfloat16 units emulates it: its peak takes minutes and no figure reads it
    unless a variant runs in bf16."""
    from bench import hardware

    monkeypatch.setattr(hardware, "matmul_peak_gflops", lambda *a, **k: 1.0)
    assert learner.peak_worker(cpu, 0.01, bf16=False) == {"fp32": 1.0}
    assert learner.peak_worker(cpu, 0.01, bf16=True) == {"fp32": 1.0, "bf16": 1.0}
    assert learner.uses_bf16(["nasa_td3+bf16"]) and not learner.uses_bf16(["td3_ae", "sac_ae"])
    args = learner.parse_args(["--variants", "nasa_td3+bf16"])
    assert "nasa_td3+bf16" in learner.worker_command(args, "peak", tmp_path / "batch.npz", False)
