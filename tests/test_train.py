"""The single-process trainer: run folder, determinism, exact resume, CLI errors."""

import errno
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nasa.train import CHECKPOINT_FILE, Trainer
from shared.config import default_config
from shared.recorder import Recorder
from shared.replay import log as rlog
from shared.replay.log import list_numbered
from shared.runlog import read_rows

VOLATILE = {"steps_per_s", "wall_s"}  # timing columns differ between runs by nature


def tiny_config(algo: str = "nasa_td3", steps: int = 80):
    config = default_config(algo, "cpu-small")
    config.steps = steps
    config.warmup_steps = 15
    config.batch_size = 8
    config.eval_every = 40
    config.eval_episodes = 1
    config.checkpoint_every = 1  # at every episode end
    config.replay_capacity = 1000
    config.device = "cpu"
    config.env.image_size = 32
    config.env.action_repeat = 25  # 40-step cartpole episodes
    config.agent.latent_dim = 16
    config.agent.hidden_dim = 32
    config.agent.ensemble_hidden_dim = 16
    config.agent.num_filters = 8
    return config


def stable_rows(path):
    return [{k: v for k, v in row.items() if k not in VOLATILE} for row in read_rows(path)]


def test_seeded_run_is_deterministic_and_writes_the_run_folder(tmp_path):
    for name in ("a", "b"):
        Trainer.create(tiny_config(), tmp_path / name).run()
    for name in ("config.json", "eval.csv", "train.csv", CHECKPOINT_FILE):
        assert (tmp_path / "a" / name).is_file()
    train = stable_rows(tmp_path / "a" / "train.csv")
    assert [r["step"] for r in train] == ["40", "80"]
    assert train[1]["critic_loss"] and train[1]["novelty_mean"] and train[1]["ensemble_loss"]
    evals = read_rows(tmp_path / "a" / "eval.csv")
    assert [r["step"] for r in evals] == ["0", "40", "80"]
    # Each evaluation is played by the weights of its step: G (1) updates a step after warm-up (15).
    assert [r["updates"] for r in evals] == ["0", "25", "65"]
    assert all(r["min"] == r["max"] == r["return_0"] for r in evals)  # one episode
    assert train == stable_rows(tmp_path / "b" / "train.csv")
    assert stable_rows(tmp_path / "a" / "eval.csv") == stable_rows(tmp_path / "b" / "eval.csv")


def test_a_budget_that_ends_mid_episode_evaluates_the_final_policy_and_extends_exactly(tmp_path):
    """Step 60 is neither an eval step (every 40) nor an episode end (every 40): the final policy is
    evaluated there all the same; a longer budget resumes from the checkpoint at 40 and drops it."""
    Trainer.create(tiny_config(steps=60), tmp_path / "run").run()
    assert [r["step"] for r in read_rows(tmp_path / "run" / "eval.csv")] == ["0", "40", "60"]
    Trainer.resume(tmp_path / "run", steps=80).run()
    assert [r["step"] for r in read_rows(tmp_path / "run" / "eval.csv")] == ["0", "40", "80"]


@pytest.mark.parametrize("algo", ["nasa_td3", "sac_ae"])
def test_resume_continues_exactly(tmp_path, algo):
    Trainer.create(tiny_config(algo, steps=80), tmp_path / "straight").run()
    # Stop mid-episode at 60: the checkpoint at 40 is the last, so resuming must
    # drop replay items and log rows written after it.
    Trainer.create(tiny_config(algo, steps=60), tmp_path / "resumed").run()
    Trainer.resume(tmp_path / "resumed", steps=80).run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(tmp_path / "resumed" / name) == stable_rows(tmp_path / "straight" / name)


@pytest.mark.parametrize("same_episodes", [False, True])
def test_resume_continues_exactly_on_the_gripper_stand_in(tmp_path, same_episodes):
    """The stand-in carries the valve and the fingers from one episode into the next, in training
    and in evaluation: a resumed run must get them back as they were, and with
    --eval-same-episodes evaluate the episodes the run began with."""
    def config(steps):
        c = tiny_config(steps=steps)
        c.env.task = "gripper-valve"
        c.env.action_repeat = 5  # 10-step episodes
        c.eval_same_episodes = same_episodes
        return c

    Trainer.create(config(80), tmp_path / "straight").run()
    Trainer.create(config(65), tmp_path / "resumed").run()  # the last checkpoint is at 60
    Trainer.resume(tmp_path / "resumed", steps=80).run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(tmp_path / "resumed" / name) == stable_rows(tmp_path / "straight" / name)


def test_a_resume_that_cannot_get_back_evicted_rows_says_so(tmp_path, capsys):
    # Capacity 50 and a checkpoint at 40: the steps after it evict rows the checkpoint's replay held.
    small = tiny_config(steps=60)
    small.replay_capacity = 50
    Trainer.create(small, tmp_path / "run").run()
    capsys.readouterr()
    Trainer.resume(tmp_path / "run", steps=80)
    assert "holds 30 of the 40 rows it held at the checkpoint" in capsys.readouterr().out
    Trainer.create(tiny_config(steps=60), tmp_path / "roomy").run()  # capacity 1000: nothing evicted
    capsys.readouterr()
    Trainer.resume(tmp_path / "roomy", steps=80)
    assert "rows it held" not in capsys.readouterr().out


def test_the_replay_log_is_compacted_at_checkpoints_and_a_resume_continues_exactly(tmp_path, straight_120):
    """A snapshot at a checkpoint replaces the log before it, so the replay folder does not grow
    with the run's whole history and a resume reads the snapshot, not every record."""
    stopped = Trainer.create(tiny_config(steps=100), tmp_path / "resumed")  # checkpoints at 40, 80
    stopped.snapshot_every = 30
    stopped.run()
    segments, snapshots = list_numbered(tmp_path / "resumed" / "replay")
    assert len(snapshots) == 1 and min(segments) == snapshots[0]  # the log before it is gone
    Trainer.resume(tmp_path / "resumed", steps=120).run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(tmp_path / "resumed" / name) == stable_rows(straight_120 / name)


def test_a_compaction_that_fails_is_said_once_and_loses_nothing(tmp_path, straight_120, monkeypatch, capsys):
    def no_room(path, sections):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rlog, "write_snapshot", no_room)
    stopped = Trainer.create(tiny_config(steps=100), tmp_path / "resumed")
    stopped.snapshot_every = 30
    stopped.run()
    monkeypatch.undo()
    assert capsys.readouterr().out.count("compacting the replay log failed, the log is kept") == 1
    assert list_numbered(tmp_path / "resumed" / "replay")[1] == []
    Trainer.resume(tmp_path / "resumed", steps=120).run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(tmp_path / "resumed" / name) == stable_rows(straight_120 / name)


def test_existing_run_folder_is_not_overwritten(tmp_path):
    Trainer.create(tiny_config(steps=40), tmp_path / "run").run()
    with pytest.raises(FileExistsError, match="--resume"):
        Trainer.create(tiny_config(steps=40), tmp_path / "run")


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "nasa.cli", "train", *args], capture_output=True, text=True, timeout=300
    )


@pytest.mark.system  # a `nasa train` process, stopped with Ctrl-C (SIGINT) or SIGTERM (`docker stop`)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_stops_cleanly_and_says_how_to_continue(tmp_path, signum):
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "nasa.cli", "train", "--task", "gripper-valve", "--preset", "cpu-small",
         "--image-size", "32", "--steps", "100000", "--eval-episodes", "1", "--checkpoint-every", "1",
         "--out", str(run)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 240
        while not (run / CHECKPOINT_FILE).exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        assert (run / CHECKPOINT_FILE).exists(), "no checkpoint within the deadline"
        proc.send_signal(signum)
        _, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signum, stderr  # the shell's convention: 130, 143
    assert "nasa train: stopped at step" in stderr and "its last checkpoint holds step" in stderr
    assert f"continue with: nasa train --resume {run}" in stderr
    assert "Traceback" not in stderr and "EGLError" not in stderr, stderr  # nor the renderer's teardown
    trainer = Trainer.resume(run)  # the folder continues
    try:
        assert trainer.counters.env_steps == trainer.last_checkpoint_step > 0
    finally:
        trainer.close()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--task", "cartpole-juggle"], "unknown task 'cartpole-juggle'; valid tasks are"),
        (["--batch-size", "0"], "batch_size must be >= 1"),
        (["--device", "cuda"], "CUDA is not available"),
        (["--preset", "huge"], "unknown preset 'huge'"),
    ],
)
@pytest.mark.system  # a `nasa train` process
def test_cli_rejects_bad_input_with_a_clear_message(tmp_path, args, message):
    import torch

    if args[:2] == ["--device", "cuda"] and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    result = run_cli("--out", str(tmp_path / "run"), *args)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (lambda state: {**state, "format": 1}, "has format 1 and this version reads format 3"),
        (None, "is not a readable checkpoint"),
        (lambda state: {**state, "env_rng": {**state["env_rng"], "keys": [1, 2, 3]}},
         "its env_rng does not fit task ball_in_cup-catch"),
        (lambda state: {k: v for k, v in state.items() if k != "eval_env_rng"},
         "its eval_env_rng does not fit task ball_in_cup-catch"),
    ],
)
@pytest.mark.system  # a `nasa train` process
def test_resume_refuses_a_checkpoint_it_cannot_continue_and_leaves_the_run_as_it_was(
    tmp_path, spoil, message
):
    import torch

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=40), run).run()
    path = run / CHECKPOINT_FILE
    if spoil is None:
        path.write_bytes(b"not a checkpoint" * 64)
    else:
        torch.save(spoil(torch.load(path, weights_only=True)), path)
    before = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    result = run_cli("--resume", str(run), "--steps", "80")
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    after = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    after = {name: data for name, data in after.items() if name.name != ".lock"}  # the run's lock
    assert after == before


@pytest.mark.system  # a `nasa train` process
def test_resume_refuses_a_run_whose_checkpoint_is_gone_and_leaves_its_rows(tmp_path):
    """Taken for a run killed before its first checkpoint, it would start over and erase its rows."""
    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=80), run).run()  # rows and checkpoints at 40 and 80
    (run / CHECKPOINT_FILE).unlink()  # deleted for space, or left out of a copy
    before = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    result = run_cli("--resume", str(run), "--steps", "120")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert (f"has no {CHECKPOINT_FILE}, though its train.csv goes on past the one saved at step 40"
            in result.stderr)
    after = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    assert {n: d for n, d in after.items() if n.name != ".lock"} == before


def test_resume_of_a_run_without_a_checkpoint_says_that_it_starts_over(tmp_path, capsys):
    """A budget that ends within the first episode past checkpoint_every leaves no checkpoint
    (they are taken at episode ends): resumed to a larger budget, the run starts again from step 0,
    and the user is told so rather than finding eval.csv emptied."""
    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=20), run).run()  # 40-step episodes: no episode end, no checkpoint
    assert not (run / CHECKPOINT_FILE).exists() and read_rows(run / "eval.csv")
    capsys.readouterr()
    Trainer.resume(run, steps=40).close()
    said = capsys.readouterr().out
    assert f"{run} has no {CHECKPOINT_FILE}" in said and "starts over from step 0" in said, said


@pytest.mark.parametrize("damage", [b"\xff\xfe\x00 not text", b"a,b,c\n0,1,2\n"])
@pytest.mark.system  # a `nasa train` process
def test_resume_refuses_a_damaged_eval_csv_and_leaves_the_run_as_it_was(tmp_path, damage):
    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=40), run).run()
    (run / "eval.csv").write_bytes(damage)
    before = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    result = run_cli("--resume", str(run), "--steps", "80")
    assert result.returncode == 2, result.stderr
    assert f"{run / 'eval.csv'} does not start with the header this run writes" in result.stderr
    assert "Traceback" not in result.stderr
    after = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    assert {name: data for name, data in after.items() if name.name != ".lock"} == before


def test_a_run_log_is_continued_only_under_its_own_header(tmp_path):
    from shared.runlog import CsvLog, RunLogError

    fields = ["step", "mean"]
    empty = tmp_path / "empty.csv"
    empty.write_bytes(b"")  # a file created and never written: nothing to lose, so it is started
    CsvLog(empty, fields).append({"step": 0, "mean": 1.5})
    assert read_rows(empty) == [{"step": "0", "mean": "1.5"}]

    foreign = tmp_path / "foreign.csv"
    foreign.write_bytes(b"step,return\n0,1\n")
    with pytest.raises(RunLogError, match="foreign.csv does not start with the header"):
        CsvLog(foreign, fields)
    assert foreign.read_bytes() == b"step,return\n0,1\n"

    # A damaged byte in a row does not stop counting or cutting the rows (a resume drops it anyway).
    damaged = tmp_path / "damaged.csv"
    damaged.write_bytes(b"step,mean\r\n0,1\r\n1,\xff\r\n2,3\r\n")
    log = CsvLog(damaged, fields)
    assert log.rows() == 3
    log.truncate(1)
    assert damaged.read_bytes() == b"step,mean\r\n0,1\r\n"


def test_a_row_its_writer_did_not_finish_is_dropped_before_the_next_one(tmp_path):
    from shared.recorder import Recorder

    (tmp_path / "eval.csv").write_bytes(
        b"step,mean,std,return_0,return_1\r\n1000,12.5,0.5,12,13\r\n2000,30,1")  # died mid-row
    recorder = Recorder(tmp_path, 2)
    assert recorder.last_eval() == {"step": 1000, "mean": 12.5, "std": 0.5}
    recorder.eval_row(2000, [300.0, 310.0], updates=1000)
    rows = read_rows(tmp_path / "eval.csv")
    assert [(r["step"], r["mean"], r["return_0"]) for r in rows] == [
        ("1000", "12.5", "12"), ("2000", "305", "300")]
    # A finished but damaged last row: the newest readable one is the last evaluation.
    with open(tmp_path / "eval.csv", "ab") as f:
        f.write(b"3000,,\r\n")
    assert Recorder(tmp_path, 2).last_eval()["step"] == 2000


def test_a_checkpoint_fsyncs_the_csv_rows_it_counts_before_it_is_written_and_its_rename_after(
    tmp_path, monkeypatch,
):
    """After a power loss the CSVs must hold at least the rows the checkpoint says they hold, and
    the folder the new checkpoint's name (an fsynced file renamed into place is not enough)."""
    import os

    from shared import checkpoint

    trainer = Trainer.create(tiny_config(steps=40), tmp_path / "run")
    try:
        trainer.run()
        events: list[str] = []
        real_fsync, real_save = os.fsync, checkpoint.save
        monkeypatch.setattr(os, "fsync", lambda fd: (events.append(os.readlink(f"/proc/self/fd/{fd}")),
                                                     real_fsync(fd))[1])
        monkeypatch.setattr(checkpoint, "save", lambda *a: (events.append("save"), real_save(*a))[1])
        trainer.save_checkpoint()
    finally:
        trainer.close()
    saved = events.index("save")
    synced = {Path(e).name for e in events[:saved]}
    assert {"eval.csv", "train.csv"} <= synced, events
    after = events[saved + 1:]
    run = os.path.realpath(tmp_path / "run")
    assert run in after and after.index(run) > after.index(f"{run}/{CHECKPOINT_FILE}.tmp"), events


def test_resume_to_a_total_the_checkpoint_already_holds_is_refused_and_keeps_the_rows(tmp_path):
    from shared.config import ConfigError

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=40), run).run()  # 40-step episodes: its checkpoint holds step 40
    before = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    for steps in (20, 40):
        with pytest.raises(ConfigError, match=f"--steps {steps}: the run's checkpoint already holds step 40"):
            Trainer.resume(run, steps=steps)
    after = {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    assert after == before


def test_a_ctrl_c_during_a_checkpoint_waits_for_it_and_then_interrupts(tmp_path):
    import os

    from shared import checkpoint

    path = tmp_path / "checkpoint.pt"
    with pytest.raises(KeyboardInterrupt), checkpoint.stop_signals_deferred():
        os.kill(os.getpid(), signal.SIGINT)  # arrives while the checkpoint is being written
        time.sleep(0.05)
        checkpoint.save(path, {"step": 7})
    assert checkpoint.load(path)["step"] == 7
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is back

    with checkpoint.stop_signals_deferred():  # no Ctrl-C: nothing is raised afterwards
        checkpoint.save(path, {"step": 8})
    assert checkpoint.load(path)["step"] == 8


def test_a_checkpoint_with_a_damaged_byte_or_of_another_algorithm_is_refused(tmp_path):
    import torch

    from shared import checkpoint
    from shared.agents import make_agent

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=40), run).run()
    path = run / CHECKPOINT_FILE
    good = path.read_bytes()
    body = bytearray(good)
    body[len(body) // 2] ^= 0x01  # one bit inside the tensor data, most of the file
    path.write_bytes(bytes(body))
    with pytest.raises(checkpoint.CheckpointError, match="fails its checksum|not a readable checkpoint"):
        checkpoint.load(path)
    path.write_bytes(good)
    state = checkpoint.load(path)
    for algo in ("pixel_td3", "sac_ae"):  # a nasa_td3 checkpoint: more networks, or other ones
        c = tiny_config(algo)
        other = make_agent(algo, (9, 32, 32), 2, c.agent, torch.device("cpu"))
        before = {k: v.clone() for k, v in other.policy_state_dict().items()}
        with pytest.raises(checkpoint.CheckpointError, match="does not fit this run's algorithm"):
            Recorder(tmp_path / algo, 2).restore(state, other, np.random.default_rng(0), truncate=False)
        assert all(torch.equal(before[k], v) for k, v in other.policy_state_dict().items())


class FullFile:
    """A file on a disk with `room` bytes left: writes past it fail with ENOSPC."""

    def __init__(self, f, room: int = 0) -> None:  # noqa: ANN001
        self.f, self.room = f, room

    def write(self, data):  # noqa: ANN001, ANN201
        if self.room <= 0:
            import errno
            import os

            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.f.write(data)

    def writelines(self, lines) -> None:  # noqa: ANN001
        for line in lines:
            self.write(line)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self.f, name)

    def __enter__(self):  # noqa: ANN204
        return self

    def __exit__(self, *exc: object) -> None:
        self.f.close()


class DiskFull:
    """ENOSPC at one of the run's writes once the run reaches `at` steps (a disk that fills)."""

    def __init__(self, monkeypatch, where: str, trainer: Trainer, at: int = 70) -> None:
        import errno
        import os

        from shared import checkpoint, runlog

        self.trainer, self.at, self.fired = trainer, at, False
        full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        if where == "csv":
            real_append = runlog.CsvLog.append

            def append(log, row):
                if self.due():
                    with open(log.path, "ab") as f:
                        f.write(b"80,3,12.5")  # the part of the row that fitted
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(log.path))
                real_append(log, row)

            monkeypatch.setattr(runlog.CsvLog, "append", append)
        elif where == "checkpoint":
            def fake_open(path, mode="r", *a, **k):
                # The checkpoint's writes fail part way (torch then raises its own error).
                f = open(path, mode, *a, **k)
                return FullFile(f, room=1000) if self.due() else f

            monkeypatch.setattr(checkpoint, "open", fake_open, raising=False)
        elif where == "replay":
            real_write = os.write

            def write(fd, data):
                log = trainer.store._log
                if log is not None and fd == log._fd and self.due():
                    return real_write(fd, bytes(data)[: len(data) // 2])  # a short write
                return real_write(fd, data)

            monkeypatch.setattr(os, "write", write)
        else:  # tensorboard: its writing thread meets the full disk; the writer raises it later
            from tensorboard.summary.writer.record_writer import RecordWriter

            real_write_record = RecordWriter.write

            def write_record(writer, data):
                if self.due():
                    raise full
                real_write_record(writer, data)

            monkeypatch.setattr(RecordWriter, "write", write_record)

    def due(self) -> bool:
        self.fired = self.fired or self.trainer.counters.env_steps >= self.at
        return self.fired


@pytest.fixture(scope="module")
def straight_120(tmp_path_factory) -> Path:
    """An uninterrupted 120-step run, the one a resumed run must equal."""
    out = tmp_path_factory.mktemp("straight") / "run"
    Trainer.create(tiny_config(steps=120), out).run()
    return out


@pytest.mark.parametrize("where", ["csv", "checkpoint", "replay", "tensorboard"])
def test_a_full_disk_stops_the_run_in_one_line_and_the_run_resumes_exactly(
    tmp_path, monkeypatch, capsys, where, straight_120
):
    from nasa.cli import run_until_stopped

    out = tmp_path / "full"
    trainer = Trainer.create(tiny_config(steps=120), out)
    with monkeypatch.context() as patch:
        fault = DiskFull(patch, where, trainer)
        with pytest.raises(SystemExit) as stop:
            run_until_stopped(trainer, out)
    assert fault.fired
    err = capsys.readouterr().err
    assert stop.value.code == 1, err
    assert "cannot write the run folder: No space left on device" in err, err
    assert f"continue with: nasa train --resume {out}" in err
    assert "Traceback" not in err, err
    held = trainer.last_checkpoint_step
    assert 0 < held < 120 or where == "tensorboard", held
    resumed = Trainer.resume(out)
    assert resumed.counters.env_steps == held
    resumed.run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(out / name) == stable_rows(straight_120 / name)


def test_cutting_a_run_log_writes_nothing_so_a_full_disk_loses_none_of_its_rows(tmp_path, monkeypatch):
    import builtins

    from shared import runlog

    path = tmp_path / "train.csv"
    path.write_bytes(b"step,mean\r\n0,1\r\n1,2\r\n2,3\r\n")
    log = runlog.CsvLog(path, ["step", "mean"])

    monkeypatch.setattr(runlog, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
    log.truncate(2)
    assert path.read_bytes() == b"step,mean\r\n0,1\r\n1,2\r\n"


def test_a_resume_on_a_full_disk_is_one_line_and_keeps_the_run(tmp_path, monkeypatch, capsys):
    import errno
    import os

    from nasa import cli
    from shared.replay.store import ReplayStore

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=60), run).run()  # its checkpoint holds step 40

    def full(store, n):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(run / "replay" / "log-000002.bin"))

    monkeypatch.setattr(ReplayStore, "truncate", full)
    with pytest.raises(SystemExit) as stop:
        cli.main(["train", "--resume", str(run), "--steps", "80"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "cannot write the run folder: No space left on device" in err, err
    monkeypatch.undo()
    trainer = Trainer.resume(run, steps=80)
    assert trainer.counters.env_steps == 40
    trainer.close()


def diverge_at(trainer: Trainer, step: int, episode_step: int) -> None:
    """The training simulation diverges whenever an episode reaches `episode_step` at run step `step`:
    a fault that depends on the run's state alone, so an exact resume meets it again."""
    from shared import envs

    real_step = trainer.env.step

    def step_or_diverge(action):
        if (trainer.counters.env_steps, trainer.loop.episode_length) == (step, episode_step):
            raise envs.EnvFault("the simulation diverged: (injected)")
        return real_step(action)

    trainer.env.step = step_or_diverge


def test_an_env_fault_abandons_the_episode_and_a_resume_continues_exactly(tmp_path, capsys):
    straight = Trainer.create(tiny_config(steps=120), tmp_path / "straight")
    diverge_at(straight, 50, 10)
    straight.run()
    assert "episode abandoned at step 50, episode step 10: the simulation diverged" in capsys.readouterr().out
    # The abandoned episode has no row, and the next one starts at step 50.
    assert [r["step"] for r in read_rows(tmp_path / "straight" / "train.csv")] == ["40", "90"]
    assert [r["episode"] for r in read_rows(tmp_path / "straight" / "train.csv")] == ["1", "2"]

    stopped = Trainer.create(tiny_config(steps=70), tmp_path / "resumed")  # its last checkpoint: 40
    diverge_at(stopped, 50, 10)
    stopped.run()
    resumed = Trainer.resume(tmp_path / "resumed", steps=120)
    diverge_at(resumed, 50, 10)
    resumed.run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(tmp_path / "resumed" / name) == stable_rows(tmp_path / "straight" / name)


def test_sac_aes_burst_is_made_once_where_the_environment_faults_at_its_step(tmp_path, capsys):
    """--algo sac_ae makes a step's updates before it steps the environment: where that step
    faults and is taken again after a reset, its updates (here the burst) are not made again."""
    from tests.test_reference_loop import sac_ae_reference_counts

    steps = 30
    trainer = Trainer.create(tiny_config("sac_ae", steps=steps), tmp_path / "run")
    warmup = trainer.config.warmup_steps
    diverge_at(trainer, warmup, warmup)  # the first episode's step `warmup`: the burst's
    trainer.run()
    assert f"episode abandoned at step {warmup}, episode step {warmup}" in capsys.readouterr().out
    assert trainer.agent.num_updates == sac_ae_reference_counts(steps, warmup)[-1] == steps - 1


def test_a_policy_that_acts_nan_stops_the_run_in_one_line_after_a_few_faults(
    tmp_path, monkeypatch, capsys
):
    from nasa import train
    from nasa.cli import run_until_stopped

    def collect_action(agent, obs, warming_up, rng, action_dim):
        return rng.uniform(-1, 1, action_dim) if warming_up else np.full(action_dim, np.nan)

    monkeypatch.setattr(train, "collect_action", collect_action)
    trainer = Trainer.create(tiny_config(steps=80), tmp_path / "run")
    with pytest.raises(SystemExit) as stop:
        run_until_stopped(trainer, tmp_path / "run")
    err = capsys.readouterr().err
    assert stop.value.code == 1
    assert (f"stopped at step 15: the environment faulted in {train.MAX_FAULTS_IN_A_ROW} episodes in a "
            "row (the last at step 15, episode step 0: action has non-finite values") in err, err
    assert "Traceback" not in err


def test_a_reset_the_environment_faults_at_stops_the_run_in_one_line_and_it_resumes(
    tmp_path, capsys
):
    from nasa.cli import run_until_stopped
    from shared import envs

    trainer = Trainer.create(tiny_config(steps=80), tmp_path / "run")
    reset = trainer.env.reset
    calls = [0]

    def reset_faulting_from_the_third(*args, **kwargs):
        calls[0] += 1
        if calls[0] >= 2:  # the second episode's reset, after the checkpoint at 40
            raise envs.EnvFault(f"the simulation diverged at each of {envs.RESET_TRIES} resets: test")
        return reset(*args, **kwargs)

    trainer.env.reset = reset_faulting_from_the_third
    with pytest.raises(SystemExit) as stop:
        run_until_stopped(trainer, tmp_path / "run")
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "diverged at each of 3 resets" in err and "Traceback" not in err
    assert Trainer.resume(tmp_path / "run").counters.env_steps == 40


def test_an_evaluation_the_environment_faults_in_leaves_no_row_and_the_run_goes_on(tmp_path, capsys):
    from shared import envs

    trainer = Trainer.create(tiny_config(steps=80), tmp_path / "run")
    real_step = trainer.eval_env.step

    def step(action):
        if trainer.counters.env_steps == 40:
            raise envs.EnvFault("the simulation diverged: (injected)")
        return real_step(action)

    trainer.eval_env.step = step
    trainer.run()
    assert "eval step 40: evaluation failed, no result for this step" in capsys.readouterr().out
    assert [r["step"] for r in read_rows(tmp_path / "run" / "eval.csv")] == ["0", "80"]


def test_a_sigterm_while_a_resume_reads_the_replay_log_is_one_line_and_the_run_resumes(
    tmp_path, monkeypatch, capsys
):
    import os

    from nasa import cli
    from shared.replay.store import ReplayStore

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=60), run).run()  # its checkpoint holds step 40
    real_replay = ReplayStore._replay

    def replay_then_sigterm(store, rtype, payload):
        real_replay(store, rtype, payload)
        if store._num_inserted == 30:
            os.kill(os.getpid(), signal.SIGTERM)  # `docker stop` while the log is read back
            time.sleep(0.05)

    monkeypatch.setattr(ReplayStore, "_replay", replay_then_sigterm)

    def unhandled(signum, frame):  # where `nasa train` would have died without a word
        raise RuntimeError("SIGTERM met no handler of nasa train's")

    signal.signal(signal.SIGTERM, unhandled)
    with pytest.raises(SystemExit) as stop:
        cli.main(["train", "--resume", str(run), "--steps", "80"])
    err = capsys.readouterr().err
    assert stop.value.code == 128 + signal.SIGTERM, err
    assert f"stopped before the run began; continue with: nasa train --resume {run}" in err
    assert "Traceback" not in err
    monkeypatch.undo()
    Trainer.resume(run, steps=80).run()
    Trainer.create(tiny_config(steps=80), tmp_path / "straight").run()
    for name in ("train.csv", "eval.csv"):
        assert stable_rows(run / name) == stable_rows(tmp_path / "straight" / name)


def test_a_checkpoint_reads_cuda_random_states_only_where_the_run_touched_cuda(monkeypatch):
    """On a GPU machine a CPU run must not open a CUDA context at each checkpoint to save states it
    never drew from (reading them initialises CUDA)."""
    import torch

    from shared import checkpoint

    def opens_a_context() -> list:
        raise AssertionError("read the CUDA random states of a run that never used CUDA")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", opens_a_context)
    assert "cuda" not in checkpoint.rng_state(np.random.default_rng(0))
    states = [torch.zeros(16, dtype=torch.uint8)]
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: states)
    assert checkpoint.rng_state(np.random.default_rng(0))["cuda"] is states


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_that_rings_inside_a_c_call_still_stops_cleanly(
    tmp_path, monkeypatch, capsys, signum
):
    """A stop signal's exception raised in Python code that a C extension calls back (ctypes
    converting an argument, as PyOpenGL's EGL calls do while a frame renders) comes out as the
    extension's own error (ctypes.ArgumentError): the run still stops as for the signal."""
    import ctypes
    import time

    from nasa.cli import run_until_stopped

    class Rings:
        @classmethod
        def from_param(cls, _obj):
            signal.raise_signal(signum)
            time.sleep(5)  # the handler raises here, inside ctypes' conversion
            return 0

    call = ctypes.CDLL(None).abs
    call.argtypes = [Rings]
    out = tmp_path / "run"
    trainer = Trainer.create(tiny_config(steps=120), out)
    step = trainer.loop.step

    def rendering(action, version):
        if trainer.counters.env_steps == 30:
            call(1)
        return step(action, version)

    monkeypatch.setattr(trainer.loop, "step", rendering)
    with pytest.raises(SystemExit) as stop:
        run_until_stopped(trainer, out)
    err = capsys.readouterr().err
    assert stop.value.code == 128 + signum, err
    assert "nasa train: stopped at step 30" in err and "Traceback" not in err, err
    assert f"continue with: nasa train --resume {out}" in err
