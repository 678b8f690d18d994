"""nasa reproduce: planning from the results folder, the dry run, errors, and running fake jobs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tyro

from nasa import reproduce as rep
from nasa.cli import TrainCommand, main
from nasa.reproduce import Run, execute, plan_runs, run_folder, train_command
from shared.config import default_config, to_dict
from shared.runlog import TRAIN_FIELDS, CsvLog, checkpointed_step, eval_fields

TASKS = ["cartpole-balance", "walker-walk"]
ALGOS = ["nasa_td3", "sac_ae"]
SEEDS = [0, 1]


def make_run(out: Path, task: str, algo: str, seed: int, total: int, last: int | None, ckpt: bool) -> None:
    """A run folder as the trainer leaves it: config.json, eval rows up to `last`, maybe a checkpoint."""
    out.mkdir(parents=True)
    config = default_config(algo, "paper", task)
    config.seed, config.steps, config.env.task = seed, total, task
    (out / "config.json").write_text(json.dumps(to_dict(config)))
    log = CsvLog(out / "eval.csv", eval_fields(1))
    for step in range(0, (last if last is not None else -1) + 1, 100):
        log.append({"step": step, "mean": 1.0, "std": 0.0, "return_0": 1.0})
    if ckpt:
        (out / "checkpoint.pt").write_bytes(b"fake")


@pytest.fixture
def results(tmp_path: Path) -> Path:
    root = tmp_path / "results"

    def make(task: str, algo: str, seed: int, total: int, last: int | None, ckpt: bool) -> None:
        make_run(run_folder(root, task, algo, seed), task, algo, seed, total, last, ckpt)

    make("cartpole-balance", "nasa_td3", 0, total=1000, last=1000, ckpt=True)  # finished
    make("cartpole-balance", "nasa_td3", 1, total=1000, last=500, ckpt=True)  # partial
    make("cartpole-balance", "sac_ae", 0, total=500, last=500, ckpt=True)  # finished at its own total
    make("walker-walk", "sac_ae", 1, total=1000, last=0, ckpt=False)  # killed before its first checkpoint
    return root


def actions(runs: list[Run]) -> dict[tuple[str, str, int], str]:
    return {(r.task, r.algo, r.seed): r.action for r in runs}


def test_plan_start_resume_skip(results: Path) -> None:
    runs = plan_runs(results, TASKS, ALGOS, SEEDS, steps=None)
    assert len(runs) == 8
    assert all(r.out == results / r.task / r.algo / f"seed{r.seed}" for r in runs)
    expected = {(t, a, s): "start" for t in TASKS for a in ALGOS for s in SEEDS}
    expected |= {
        ("cartpole-balance", "nasa_td3", 0): "skip",
        ("cartpole-balance", "nasa_td3", 1): "resume",
        ("cartpole-balance", "sac_ae", 0): "skip",
        ("walker-walk", "sac_ae", 1): "resume",
    }
    assert actions(runs) == expected


def test_plan_with_a_longer_total_extends_finished_runs(results: Path) -> None:
    got = actions(plan_runs(results, TASKS, ALGOS, SEEDS, steps=1000))
    assert got["cartpole-balance", "nasa_td3", 0] == "skip"
    assert got["cartpole-balance", "sac_ae", 0] == "resume"  # reached 500, 1000 asked for
    assert got["cartpole-balance", "nasa_td3", 1] == "resume"


def test_plan_changes_nothing(results: Path) -> None:
    before = sorted(p.relative_to(results) for p in results.rglob("*"))
    plan_runs(results, TASKS, ALGOS, SEEDS, steps=None)
    assert sorted(p.relative_to(results) for p in results.rglob("*")) == before


def test_start_command_is_what_nasa_train_reads(tmp_path: Path) -> None:
    run = Run("walker-walk", "sac_ae", 3, tmp_path / "walker-walk/sac_ae/seed3", "start")
    cmd = train_command(run, "paper", "cpu", 20_000, ["--eval-every", "5000"])
    assert cmd[:4] == [sys.executable, "-m", "nasa.cli", "train"]
    default = TrainCommand(config=default_config("sac_ae", "paper"))
    parsed = tyro.cli(TrainCommand, args=cmd[4:], default=default)
    assert (parsed.config.algo, parsed.config.env.task, parsed.config.seed) == ("sac_ae", "walker-walk", 3)
    assert (parsed.config.steps, parsed.config.eval_every, parsed.config.device) == (20_000, 5000, "cpu")
    assert parsed.out == run.out and parsed.preset == "paper" and parsed.resume is None


def test_resume_command(tmp_path: Path) -> None:
    run = Run("walker-walk", "sac_ae", 0, tmp_path / "r", "resume")
    assert train_command(run, "paper", "cpu", None, ["--x"])[4:] == ["--resume", str(run.out)]
    assert train_command(run, "paper", "cpu", 500, [])[4:] == ["--resume", str(run.out), "--steps", "500"]
    with pytest.raises(ValueError):
        train_command(Run("walker-walk", "sac_ae", 0, tmp_path / "r", "skip"), "paper", "cpu", None, [])


def base_args(results: Path) -> list[str]:
    return ["reproduce", "--tasks", ",".join(TASKS), "--algos", ",".join(ALGOS), "--seeds", "2",
            "--results", str(results), "--device", "cpu"]


def test_dry_run_prints_the_plan_and_launches_nothing(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_launch(*args: object, **kwargs: object) -> None:
        raise AssertionError("the dry run launched a process")

    monkeypatch.setattr(subprocess, "Popen", no_launch)
    before = sorted(results.rglob("*"))
    main([*base_args(results), "--dry-run"])
    out = capsys.readouterr().out
    assert "8 runs" in out and "4 to start, 2 to resume, 2 finished" in out
    assert f"skip   cartpole-balance nasa_td3 seed 0 -> {results}/cartpole-balance/nasa_td3/seed0" in out
    assert f"resume cartpole-balance nasa_td3 seed 1 -> {results}/cartpole-balance/nasa_td3/seed1" in out
    assert f"start  walker-walk nasa_td3 seed 0 -> {results}/walker-walk/nasa_td3/seed0" in out
    assert f"nasa train --resume {results}/walker-walk/sac_ae/seed1" in out
    assert out.count("nasa train --algo") == 4
    assert sorted(results.rglob("*")) == before


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [("--tasks", "cartpole-nope", "unknown task 'cartpole-nope'"),
     ("--algos", "nasa_td3,td4", "unknown algo 'td4'"),
     ("--seeds", "0", "--seeds must be >= 1")],
)
def test_bad_arguments_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str, value: str, message: str
) -> None:
    args = base_args(tmp_path / "results")
    args[args.index(flag) + 1] = value
    with pytest.raises(SystemExit) as exc:
        main([*args, "--dry-run"])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "results").exists()


def test_execute_runs_jobs_and_reports_failures(tmp_path: Path) -> None:
    ok = [Run("t", "a", s, tmp_path / f"ok{s}", "start") for s in range(3)]
    bad = Run("t", "a", 9, tmp_path / "bad", "start")
    jobs = [(r, [sys.executable, "-c", f"print('hello {r.seed}')"]) for r in ok]
    jobs.append((bad, [sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"]))
    failed = execute(jobs, parallel=2, poll_s=0.02)
    assert failed == [bad]
    for r in ok:
        assert (r.out / "train.log").read_text() == f"hello {r.seed}\n"
    assert "boom" in (bad.out / "train.log").read_text()


def test_a_run_that_refuses_its_input_is_named_with_its_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = Run("t", "a", 0, tmp_path / "r", "resume")
    refuses = ("import sys; print(' 50%|#####', end='\\r'); "  # a progress bar's line, then the error
               "print('nasa train: error: r/config.json is unreadable'); sys.exit(2)")
    assert execute([(run, [sys.executable, "-c", refuses])], parallel=1, poll_s=0.02) == [run]
    out = capsys.readouterr().out
    assert f"FAILED {run.out}: exit code 2, it refused its input (nasa train: error: r/config.json is " \
        "unreadable); running it again fails the same way" in out


def test_a_run_that_cannot_be_started_fails_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ok = [Run("t", "a", s, tmp_path / f"ok{s}", "start") for s in range(2)]
    bad = Run("t", "a", 9, tmp_path / "bad", "start")
    (bad.out / "train.log").mkdir(parents=True)  # its log cannot be opened, as in a folder it may not write
    jobs = [(r, [sys.executable, "-c", "print('hello')"]) for r in (ok[0], bad, ok[1])]
    assert execute(jobs, parallel=2, poll_s=0.02) == [bad]
    assert all((r.out / "train.log").read_text() == "hello\n" for r in ok)
    assert f"FAILED {bad.out}: cannot start it: Is a directory" in capsys.readouterr().out


def test_second_invocation_skips_what_the_first_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The whole command with a fake trainer that writes a finished run folder."""
    results = tmp_path / "results"
    launched: list[Run] = []

    def fake_train_command(run: Run, *args: object) -> list[str]:
        launched.append(run)
        made = default_config(run.algo, "paper", run.task)  # what nasa train writes
        made.seed, made.steps, made.env.task = run.seed, 300, run.task
        config = json.dumps(to_dict(made))
        script = (
            "import pathlib, sys; out = pathlib.Path(sys.argv[1]); "
            "(out / 'config.json').write_text(sys.argv[2]); "
            "(out / 'eval.csv').write_text('step,mean,std\\n0,1,0\\n300,2,0\\n')"
        )
        return [sys.executable, "-c", script, str(run.out), config]

    monkeypatch.setattr(rep, "train_command", fake_train_command)
    monkeypatch.setattr(rep.time, "sleep", lambda s: None)  # poll without waiting
    args = ["reproduce", "--tasks", "cartpole-balance", "--algos", "td3_ae", "--seeds", "2",
            "--results", str(results), "--device", "cpu", "--parallel", "2"]
    main(args)
    assert [(r.seed, r.action) for r in launched] == [(0, "start"), (1, "start")]
    assert "all runs finished" in capsys.readouterr().out
    launched.clear()
    main(args)
    assert launched == []
    assert "0 to start, 0 to resume, 2 finished" in capsys.readouterr().out


def test_a_second_reproduce_on_the_same_results_is_refused_before_it_starts_anything(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(rep, "execute", lambda *a, **k: pytest.fail("runs were started"))
    with rep.lock_runs(results, [("walker-walk", "sac_ae", 1)]):  # as a first `nasa reproduce` holds it
        main([*base_args(results), "--dry-run"])  # a dry run changes nothing: it may look
        assert "4 to start, 2 to resume, 2 finished" in capsys.readouterr().out
        with pytest.raises(SystemExit) as exc:
            main(base_args(results))
    err = capsys.readouterr().err
    run = run_folder(results, "walker-walk", "sac_ae", 1)
    assert exc.value.code == 2 and f"{run} is a run of another nasa reproduce" in err
    assert "nasa reproduce" in err.split(str(run), 1)[1] and err.count("\n") == 1


def test_two_reproduces_with_other_runs_share_a_results_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A lock per run, not one on the results folder: another task's runs go on beside them."""
    results = tmp_path / "results"
    monkeypatch.setattr(rep, "train_command", finishes)
    monkeypatch.setattr(rep.time, "sleep", lambda s: None)
    args = ["reproduce", "--algos", "td3_ae", "--seeds", "1", "--results", str(results), "--device", "cpu"]
    with rep.lock_runs(results, [("cartpole-balance", "td3_ae", 0)]):
        main([*args, "--tasks", "walker-walk"])
        assert "all runs finished" in capsys.readouterr().out
        with pytest.raises(SystemExit) as exc:
            main([*args, "--tasks", "walker-walk,cartpole-balance"])
        assert exc.value.code == 2 and "is a run of another nasa reproduce" in capsys.readouterr().err
    assert not run_folder(results, "cartpole-balance", "td3_ae", 0).exists()
    main([*args, "--tasks", "walker-walk,cartpole-balance"])  # released: it goes on
    assert "all runs finished" in capsys.readouterr().out


def evaluates_to(last: int):  # noqa: ANN201 -- a fake train_command
    """A fake `nasa train` (exit 0) that leaves a run of 300 steps evaluated at 0 and `last`."""

    def command(run: Run, *args: object) -> list[str]:
        made = default_config(run.algo, "paper", run.task)
        made.seed, made.steps, made.env.task = run.seed, 300, run.task
        script = ("import pathlib, sys; out = pathlib.Path(sys.argv[1]); "
                  "(out / 'config.json').write_text(sys.argv[2]); "
                  f"(out / 'eval.csv').write_text('step,mean,std\\n0,1,0\\n{last},2,0\\n')")
        return [sys.executable, "-c", script, str(run.out), json.dumps(to_dict(made))]

    return command


finishes = evaluates_to(300)
"""A fake `nasa train` that leaves a finished run of 300 steps in the run's folder."""


def test_a_run_that_ends_without_its_last_evaluation_is_not_reported_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"

    monkeypatch.setattr(rep, "train_command", evaluates_to(200))  # its final evaluation missing
    monkeypatch.setattr(rep.time, "sleep", lambda s: None)
    with pytest.raises(SystemExit) as exc:
        main(["reproduce", "--tasks", "cartpole-balance", "--algos", "td3_ae", "--seeds", "1",
              "--results", str(results), "--device", "cpu"])
    out, err = capsys.readouterr()
    assert exc.value.code == 1 and "all runs finished" not in out
    assert f"UNFINISHED {results / 'cartpole-balance' / 'td3_ae' / 'seed0'}" in err


def test_a_run_whose_checkpoint_is_gone_is_not_started_over(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(rep, "execute", lambda *a, **k: pytest.fail("runs were started"))
    out = run_folder(results, "cartpole-balance", "nasa_td3", 1)  # evaluated up to 500 of 1000
    log = CsvLog(out / "train.csv", TRAIN_FIELDS)
    # checkpoint_every is 10000 (paper): checkpointed at the end of the episode of step 10000
    for episode, step in enumerate((9000, 10000, 11000), 1):
        log.append({"step": step, "episode": episode, "return": 1.0, "length": 1000})
    (out / "checkpoint.pt").unlink()  # deleted for space, or left out of a copy
    before = (out / "eval.csv").read_bytes()
    with pytest.raises(SystemExit) as exc:
        main(base_args(results))
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"{out}: no checkpoint.pt" in err and "erase its eval.csv" in err
    assert (out / "eval.csv").read_bytes() == before


def test_a_damaged_run_folder_is_planned_for_resume_not_a_traceback(results: Path) -> None:
    broken = run_folder(results, "cartpole-balance", "nasa_td3", 0)  # finished, until its files broke
    (broken / "config.json").write_text("{not json")
    assert actions(plan_runs(results, TASKS, ALGOS, SEEDS, steps=None))["cartpole-balance", "nasa_td3", 0] \
        == "resume"  # `nasa train --resume` then names the file, and only this run fails
    (broken / "config.json").write_text(json.dumps({"steps": 1000}))
    (broken / "eval.csv").write_bytes(b"step,mean\n\xff,1\n")
    assert actions(plan_runs(results, TASKS, ALGOS, SEEDS, steps=None))["cartpole-balance", "nasa_td3", 0] \
        == "resume"


@pytest.mark.parametrize("row", ["inf,1,0,1", "nan,1,0,1"])
def test_a_step_that_is_not_a_number_is_planned_for_resume_not_a_traceback(results: Path, row: str) -> None:
    broken = run_folder(results, "cartpole-balance", "nasa_td3", 0)
    with open(broken / "eval.csv", "a") as f:
        f.write(row + "\n")
    assert actions(plan_runs(results, TASKS, ALGOS, SEEDS, steps=None))["cartpole-balance", "nasa_td3", 0] \
        == "resume"


@pytest.mark.parametrize("step", ["1e20", "100000000000000000000", "1001"])
@pytest.mark.parametrize("seed", [0, 1])  # finished, and evaluated up to 500 of 1000
def test_an_eval_step_past_the_runs_total_is_not_a_finished_run(results: Path, step: str, seed: int) -> None:
    out = run_folder(results, "cartpole-balance", "nasa_td3", seed)
    with open(out / "eval.csv", "a") as f:
        f.write(f"{step},1,0,1\n")  # the run evaluates nowhere past its total: a damaged row
    assert rep.run_state(out, steps=None) == "resume"
    assert rep.run_state(out, steps=1000) == "resume"


@pytest.mark.parametrize(("episodes", "state"), [
    ((750, 875), "resume"),  # killed after the final evaluation, before its episode's row
    ((875, 1000), "skip"),
    ((900,), "skip"),  # the total ends no episode: the last one went past it
])
def test_a_run_without_the_row_of_its_last_episode_is_not_finished(
    results: Path, episodes: tuple[int, ...], state: str
) -> None:
    out = run_folder(results, "cartpole-balance", "nasa_td3", 0)  # evaluated at its total, 1000
    log = CsvLog(out / "train.csv", TRAIN_FIELDS)
    for episode, step in enumerate(episodes, 1):
        log.append({"step": step, "episode": episode, "return": 1.0, "length": 125})
    assert rep.run_state(out, steps=None) == state


def test_a_config_json_holding_a_value_of_the_wrong_type_is_named_not_called_other_settings(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(rep, "execute", lambda *a, **k: pytest.fail("runs were started"))
    out = run_folder(results, "cartpole-balance", "nasa_td3", 1)
    body = json.loads((out / "config.json").read_text())
    (out / "config.json").write_text(json.dumps({**body, "seed": "x"}))
    before = (out / "config.json").read_bytes()
    with pytest.raises(SystemExit) as exc:
        main(base_args(results))
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "other settings" not in err
    assert f"{out / 'config.json'}: seed must be a whole number, got 'x'" in err
    assert (out / "config.json").read_bytes() == before


def test_an_unknown_flag_after_dashes_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for extra, says in ((["--bogus", "1"], "Unrecognized options: --bogus"),
                        (["--batch-size", "x"], "Error parsing --batch-size")):
        with pytest.raises(SystemExit) as exc:
            main([*base_args(tmp_path / "results"), "--dry-run", "--", *extra])
        out, err = capsys.readouterr()
        assert exc.value.code == 2 and says in err and "nasa train --help" in err
        assert err.count("\n") == 1 and not out and "╭" not in err
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("name", ["eval.csv", "train.csv"])
def test_a_field_past_the_csv_readers_limit_is_planned_for_resume_not_a_traceback(
    results: Path, name: str
) -> None:
    """A damaged file (a binary blob, an unclosed quote) can hold a field past csv's limit."""
    out = run_folder(results, "cartpole-balance", "nasa_td3", 0)  # finished
    if name == "train.csv":
        CsvLog(out / name, TRAIN_FIELDS).append({"step": 1000, "episode": 1, "length": 1000})
    with open(out / name, "a") as f:
        f.write('"' + "x" * 200_000 + "\n")
    assert rep.run_state(out, steps=None) == "resume"
    assert checkpointed_step(out, 1) is None


def test_a_last_eval_row_cut_short_is_not_a_finished_run(results: Path) -> None:
    out = run_folder(results, "cartpole-balance", "nasa_td3", 1)  # evaluated up to 500 of 1000
    with open(out / "eval.csv", "a") as f:
        f.write("1000,4")  # the final row, cut short: its writer died, or a copy stopped
    assert actions(plan_runs(results, TASKS, ALGOS, SEEDS, steps=None))["cartpole-balance", "nasa_td3", 1] \
        == "resume"


def test_results_that_name_a_file_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results").write_text("")
    with pytest.raises(SystemExit) as exc:
        main([*base_args(tmp_path / "results"), "--dry-run"])
    assert exc.value.code == 2
    assert "is a file, not a folder" in capsys.readouterr().err


def test_runs_made_with_another_preset_are_not_resumed_or_counted_as_this_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    out = run_folder(results, "cartpole-balance", "nasa_td3", 0)
    out.mkdir(parents=True)
    made = default_config("nasa_td3", "cpu-small", "cartpole-balance")
    made.env.task, made.steps = "cartpole-balance", 2000
    (out / "config.json").write_text(json.dumps(to_dict(made)))
    args = ["reproduce", "--tasks", "cartpole-balance", "--algos", "nasa_td3", "--seeds", "1",
            "--results", str(results), "--device", "cpu", "--dry-run"]
    with pytest.raises(SystemExit) as done:
        main([*args, "--preset", "paper"])
    err = capsys.readouterr().err
    assert done.value.code == 2 and "other settings than --preset paper" in err and "seed0" in err
    main([*args, "--preset", "cpu-small"])  # the settings it was made with: resumed
    assert "0 to start, 1 to resume" in capsys.readouterr().out


def test_runs_begun_before_a_default_changed_are_refused_naming_the_flags_that_continue_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A results folder begun before --updates-before-store existed: its sac_ae runs' config.json
    has no such field, so they go on storing before updating, where a new run now updates first."""
    results = tmp_path / "results"
    out = run_folder(results, "cartpole-balance", "sac_ae", 0)
    make_run(out, "cartpole-balance", "sac_ae", 0, total=1000, last=500, ckpt=True)
    body = json.loads((out / "config.json").read_text())
    del body["updates_before_store"]
    (out / "config.json").write_text(json.dumps(body))
    before = (out / "config.json").read_bytes()
    args = ["reproduce", "--tasks", "cartpole-balance", "--algos", "sac_ae", "--seeds", "1",
            "--results", str(results), "--device", "cpu", "--preset", "paper", "--dry-run"]
    with pytest.raises(SystemExit) as done:
        main(args)
    err = capsys.readouterr().err
    assert done.value.code == 2 and err.count("\n") == 1
    assert "updates_before_store (True here, False in the run)" in err
    assert "add after --: --no-updates-before-store)" in err
    main([*args, "--", "--no-updates-before-store"])  # the flag it names: the run goes on
    assert "0 to start, 1 to resume" in capsys.readouterr().out
    assert (out / "config.json").read_bytes() == before


@pytest.mark.parametrize("extra", [["--seed", "7"], ["--out=elsewhere"], ["--task", "walker-walk"],
                                   ["--preset", "cpu-small"], ["--device", "cuda"], ["--resume", "x"],
                                   ["--algo", "sac_ae"], ["--steps", "10"]])
def test_flags_after_dashes_may_not_override_each_runs_own(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*base_args(tmp_path / "results"), "--dry-run", "--", *extra])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "would override what nasa reproduce sets for each run" in err
    assert extra[0].split("=")[0] in err and not (tmp_path / "results").exists()


def test_a_bad_value_after_dashes_is_one_error_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(rep, "execute", lambda *a, **k: pytest.fail("runs were started"))
    with pytest.raises(SystemExit) as exc:
        main([*base_args(tmp_path / "results"), "--", "--batch-size", "0"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "batch_size must be >= 1" in err and "Traceback" not in err
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("value", ["0", "-1"])
def test_parallel_below_one_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*base_args(tmp_path / "results"), "--dry-run", "--parallel", value])
    assert exc.value.code == 2 and f"--parallel must be >= 1, got {value}" in capsys.readouterr().err


def test_a_camera_after_dashes_is_checked_against_every_task(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*base_args(tmp_path / "results"), "--dry-run", "--", "--camera-id", "99"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "env.camera_id 99 is not a camera of cartpole-balance" in err
    assert not (tmp_path / "results").exists()


FAKE_REPRODUCE = """
import sys
from nasa import reproduce as rep
from nasa.cli import main

def sleeper(run, *args):  # a run that records its pid and goes on until stopped; as nasa train does,
    # it asks for SIGTERM when its launcher dies
    code = ("import os, pathlib, sys, time; from shared.service import die_with_parent; die_with_parent(); "
            "pathlib.Path(sys.argv[1]).write_text(str(os.getpid())); time.sleep(600)")
    if len(sys.argv) > 2:  # a run that does not stop on SIGTERM (one stuck, or stopping slowly)
        code = ("import pathlib, signal, sys; signal.signal(signal.SIGTERM, "
                "lambda *_: pathlib.Path(sys.argv[1] + '.term').write_text('got it')); " + code)
    return [sys.executable, "-c", code, str(run.out / "pid")]

rep.train_command = sleeper
main(["reproduce", "--tasks", "cartpole-balance", "--algos", "td3_ae", "--seeds", "2", "--results",
      sys.argv[1], "--device", "cpu", "--parallel", "2"])
"""


def alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, ended but not yet reaped by whoever adopted it, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.fixture
def fake_reproduce(tmp_path: Path, request: pytest.FixtureRequest):  # noqa: ANN201 -- yields (process, its runs' pids)
    """`nasa reproduce` of two runs that go on until stopped, in its own process, once both run;
    indirect parametrization "stubborn": runs that ignore SIGTERM."""
    results = tmp_path / "results"
    stubborn = ["stubborn"] if getattr(request, "param", None) == "stubborn" else []
    proc = subprocess.Popen([sys.executable, "-c", FAKE_REPRODUCE, str(results), *stubborn],
                            cwd=Path(__file__).parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    pid_files = [run_folder(results, "cartpole-balance", "td3_ae", s) / "pid" for s in (0, 1)]
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while not all(f.exists() and f.read_text() for f in pid_files):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        pids = [int(f.read_text()) for f in pid_files]
        yield proc, pids
    finally:
        proc.kill()
        proc.communicate()
        for pid in pids:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_stopped_reproduce_stops_its_runs_and_says_so_in_one_line(
    fake_reproduce: tuple[subprocess.Popen, list[int]], signum: int, code: int
) -> None:
    proc, pids = fake_reproduce
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code
    assert "Traceback" not in err and "nasa reproduce: stopped" in err
    assert not any(alive(pid) for pid in pids)  # none left running on its own


@pytest.mark.parametrize("fake_reproduce", ["stubborn"], indirect=True)
@pytest.mark.parametrize(("second", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_second_signal_while_its_runs_stop_kills_them_and_exits_at_once(
    fake_reproduce: tuple[subprocess.Popen, list[int]], tmp_path: Path, second: int, code: int
) -> None:
    proc, pids = fake_reproduce
    proc.send_signal(signal.SIGTERM)  # the runs note the SIGTERM it passes on, and go on: the stop waits
    noted = [run_folder(tmp_path / "results", "cartpole-balance", "td3_ae", s) / "pid.term" for s in (0, 1)]
    deadline = time.monotonic() + 60
    while not all(f.exists() for f in noted) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None and all(alive(pid) for pid in pids) and all(f.exists() for f in noted)
    proc.send_signal(second)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code
    assert "nasa reproduce: forced to stop" in err and "2 run(s) under way killed" in err
    deadline = time.monotonic() + 60
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in pids)


def test_a_killed_reproduce_leaves_no_run_running(fake_reproduce: tuple[subprocess.Popen, list[int]]) -> None:
    proc, pids = fake_reproduce
    proc.kill()  # SIGKILL: it can stop nothing itself
    proc.communicate(timeout=120)
    deadline = time.monotonic() + 120  # each run gets SIGTERM from the kernel; wait for it to end
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in pids)  # else they would hold their folders from the next one


LOCK_MANY = """
import resource, sys
from pathlib import Path
from nasa import reproduce as rep
from shared.config import ConfigError

soft, hard = int(sys.argv[2]), int(sys.argv[3])
resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
runs = [("cartpole-balance", "td3_ae", seed) for seed in range(300)]
try:
    with rep.lock_runs(Path(sys.argv[1]), runs):
        print("locked", len(list(Path(sys.argv[1], ".reproduce", "cartpole-balance", "td3_ae").iterdir())))
except ConfigError as err:
    print("refused:", err)
"""


def test_more_runs_than_the_open_file_limit_allows_are_locked_or_refused_in_one_line(tmp_path: Path) -> None:
    """A lock per run holds a file open per run: the soft limit is raised to fit them, and a hard
    limit too low is one error, not a failure part way through the locks."""
    import resource

    def lock(soft: int, hard: int) -> str:
        args = [str(tmp_path / "results"), str(soft), str(hard)]
        return subprocess.run([sys.executable, "-c", LOCK_MANY, *args], cwd=Path(__file__).parents[1],
                              capture_output=True, text=True, check=True).stdout

    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    if hard != resource.RLIM_INFINITY and hard < 300 + rep.SPARE_FILES:
        pytest.skip(f"this machine's hard limit of open files, {hard}, is below what the test raises to")
    assert lock(128, hard) == "locked 300\n"
    out = lock(128, 128)
    assert out.startswith("refused: 300 runs need") and "ulimit -Hn" in out and out.count("\n") == 1


def test_a_ctrl_c_while_it_plans_is_one_line_and_exit_130(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt  # as Ctrl-C raises it, here while the folders are read

    monkeypatch.setattr(rep, "plan_runs", interrupted)
    monkeypatch.setattr(rep, "execute", lambda *a, **k: pytest.fail("runs were started"))
    handler = signal.getsignal(signal.SIGINT)
    try:
        with pytest.raises(SystemExit) as exc:
            main(base_args(results))
    finally:
        signal.signal(signal.SIGINT, handler)
    err = capsys.readouterr().err
    assert exc.value.code == 130 and err.strip() == "nasa reproduce: stopped before any run was under way"
