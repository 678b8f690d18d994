"""Issue 14, faults: one run per folder (lock), a read-only folder or a busy port is one line and exit 2,
a full disk pauses the replay's inserts without a torn record or an acknowledgement and resumes by
itself, health tells the truth, a dead worker thread is noticed."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from nasa.up import free_port
from services.learner.learner import Learner, LearnerArgs
from shared import faults, wire
from shared.replay import log as rlog
from shared.replay.client import Prefetcher
from shared.replay.store import open_store
from shared.service import StopFlag
from tests.test_learner import core_on
from tests.test_replay_service import batch, make_service

HOLD = "import sys, time; from shared.faults import lock_run; l = lock_run(sys.argv[1], 'a test run'); " \
       "print('locked', flush=True); time.sleep(120)"


@contextlib.contextmanager
def holder(data: Path):  # noqa: ANN201
    """Another process holding the run's lock, as a running `nasa up` does."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(data)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield proc
    finally:
        proc.kill()
        proc.wait()


@contextlib.contextmanager
def tmpfs(path: Path, options: str):  # noqa: ANN201
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def _nasa(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nasa.cli", *args], capture_output=True, text=True,
                          timeout=120, env=env)


# -- one run per folder ----------------------------------------------------------------------


def test_a_second_launcher_on_a_run_folder_gets_one_line_naming_the_owner(tmp_path):
    with holder(tmp_path) as first:
        with pytest.raises(faults.RunFolderError, match=f"pid {first.pid} .*a test run"):
            faults.lock_run(tmp_path, "second")
        done = _nasa("train", "--preset", "cpu-small", "--steps", "10", "--out", str(tmp_path))
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and f"pid {first.pid}" in lines[0] and "another run" in lines[0]
        assert lines[0].endswith("use another --out")  # the flag `nasa train` names its folder with
        assert first.poll() is None  # the first run is unaffected
        assert not (tmp_path / "config.json").exists()
    faults.lock_run(tmp_path, "after the first ended").close()  # kill -9 released it


def test_services_share_their_launchers_lock_and_never_a_role(tmp_path, monkeypatch):
    monkeypatch.delenv("NASA_PARENT_PID", raising=False)
    with holder(tmp_path) as launcher:
        with pytest.raises(faults.RunFolderError, match="another run"):
            faults.lock_service(tmp_path, "replay")  # not its launcher's run
        monkeypatch.setenv("NASA_PARENT_PID", str(launcher.pid))
        with faults.lock_service(tmp_path, "replay"), faults.lock_service(tmp_path, "learner"):
            with pytest.raises(faults.RunFolderError, match="has a replay already"):
                faults.lock_service(tmp_path, "replay")
    monkeypatch.delenv("NASA_PARENT_PID")
    other = tmp_path / "compose"  # services without a launcher share the folder; a launcher may not join
    with faults.lock_service(other, "replay"), faults.lock_service(other, "learner"):
        with pytest.raises(faults.RunFolderError, match="another run"):
            faults.lock_run(other, "nasa up")
    # Services that took the run's lock after a launcher had gone: the file still names the
    # launcher, which is not who holds it now.
    with holder(tmp_path / "later") as launcher:
        pass
    with faults.lock_service(tmp_path / "later", "replay"):
        with pytest.raises(faults.RunFolderError, match=f"its services; .*pid {launcher.pid} .* has exited"):
            faults.lock_run(tmp_path / "later", "nasa up")


ROLE_HOLD = "import sys, time; from shared.faults import RunLock; from pathlib import Path; " \
            "RunLock()._take(Path(sys.argv[1]) / '.lock.evaluator', True, 'the evaluator of a run'); " \
            "print('locked', flush=True); time.sleep(120)"


def test_a_launcher_waits_for_an_earlier_launchs_service_still_stopping(tmp_path, monkeypatch):
    """`nasa up` killed with SIGKILL, then started again at once: its evaluator, say, is still
    finishing an evaluation and holds its role's lock. The new launch waits for it to exit, rather
    than start an evaluator that refuses (exit 2) and run on without one."""
    orphan = subprocess.Popen([sys.executable, "-c", ROLE_HOLD, str(tmp_path)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert orphan.stdout.readline().strip() == "locked"
        said: list[str] = []

        def exits_now(msg: str) -> None:  # the orphan ends while the launcher waits for it
            said.append(msg)
            orphan.kill()
            orphan.wait()

        with faults.lock_run(tmp_path, "nasa up", say=exits_now):
            monkeypatch.setenv("NASA_PARENT_PID", str(os.getpid()))
            faults.lock_service(tmp_path, "evaluator").close()  # the new launch's evaluator starts
        assert len(said) == 1 and "the evaluator of an earlier launch" in said[0], said
        assert f"pid {orphan.pid} " in said[0]
    finally:
        orphan.kill()
        orphan.wait()
    # One that never exits (it ignores SIGTERM) is named, and the run's lock is not kept.
    with subprocess.Popen([sys.executable, "-c", ROLE_HOLD, str(tmp_path)], stdout=subprocess.PIPE,
                          text=True) as stuck:
        try:
            assert stuck.stdout.readline().strip() == "locked"
            named = f"evaluator of an earlier launch .*pid {stuck.pid} .*has not exited within 0.3 s"
            with pytest.raises(faults.RunFolderError, match=named):
                faults.lock_run(tmp_path, "nasa up", wait_s=0.3, say=lambda msg: None)
        finally:
            stuck.kill()
    faults.lock_run(tmp_path, "after it", wait_s=0.0).close()


def test_a_read_only_folder_is_one_clear_error(tmp_path):
    with tmpfs(tmp_path / "ro", "ro,size=1m") as ro:
        with pytest.raises(faults.RunFolderError, match="cannot be written"):
            faults.lock_run(ro / "run", "nasa up")
        done = _nasa("train", "--preset", "cpu-small", "--steps", "10", "--out", str(ro / "run"))
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert "cannot be written" in done.stderr


def test_a_full_disk_is_one_clear_error_for_a_launcher(tmp_path):
    # The folder's probe (an empty file) passes on a full disk; the lock's owner line cannot be written.
    with tmpfs(tmp_path / "full", "size=64k") as full:
        with contextlib.suppress(OSError):
            (full / "fill").write_bytes(b"x" * 128 * 1024)
        with pytest.raises(faults.RunFolderError, match="run cannot be written .No space left on device"):
            faults.lock_run(full / "run", "nasa up")
        done = _nasa("train", "--preset", "cpu-small", "--steps", "10", "--out", str(full / "run"))
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert "No space left on device" in done.stderr


def test_a_busy_port_is_one_line_and_exit_2(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(faults.RunFolderError, match=f"port {port} .* in use"):
            faults.check_port_free("127.0.0.1", port, "the status", "--port")
        for flag in ("--port", "--router-port"):
            done = _nasa("up", "--preset", "cpu-small", "--data", str(tmp_path / flag), flag, str(port))
            assert done.returncode == 2, done.stderr
            assert f"port {port}" in done.stderr and "Traceback" not in done.stderr
            assert f"choose another with {flag}" in done.stderr, done.stderr  # the flag that sets it
            assert not (tmp_path / flag).exists()  # refused before the run folder is made
    free = str(free_port())
    same = _nasa("up", "--preset", "cpu-small", "--data", str(tmp_path / "same"), "--port", free,
                 "--router-port", free)
    assert same.returncode == 2 and "each need a port of their own" in same.stderr, same.stderr
    assert not (tmp_path / "same").exists()


def test_a_router_that_cannot_listen_is_one_line_and_exit_2(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        for listen in (f"tcp/127.0.0.1:{busy.getsockname()[1]}", "bogus"):
            done = subprocess.run([sys.executable, "-m", "services.router", "--listen", listen],
                                  capture_output=True, text=True, timeout=120)
            assert done.returncode == 2, done.stderr  # a supervisor must not restart it in a loop
            assert f"cannot listen on {listen}" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.parametrize("module, prog, flag, meant", [
    ("services.router", "router", "--listn", "--listen"),
    ("services.robot_bridge", "robot_bridge", "--tsk", "--task"),
])
def test_a_flag_the_router_or_a_bridge_refuses_is_one_line_and_exit_2(module, prog, flag, meant):
    # They start outside `shared.service` (no learner config to read): the same one line as the rest.
    done = subprocess.run([sys.executable, "-m", module, flag, "x"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr == (f"{prog}: error: Unrecognized options: {flag}, x; did you mean {meant}? "
                           f"(`python -m {module} --help` lists its flags)\n")


def _serving(proc: subprocess.Popen, says: str) -> None:
    """Read the process's stderr until a line holds `says`."""
    for line in proc.stderr:
        if says in line:
            return
    pytest.fail(f"it exited ({proc.wait()}) before saying {says!r}")


def test_a_service_stopped_by_a_signal_exits_128_plus_it_and_one_stopped_by_the_run_exits_0(tmp_path):
    """A supervisor restarts what exited non-zero and leaves what exited 0 (the run is done): an actor
    or a learner stopped from outside must not read as finished."""
    from shared.zenoh_session import open_client

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "NASA_ZENOH_CONNECT": endpoint, "NASA_RUN_ID": "sig"}
    env.pop("NASA_ZENOH_AUTH", None)
    popen = {"stderr": subprocess.PIPE, "text": True, "env": env}
    router = subprocess.Popen([sys.executable, "-m", "services.router", "--listen", endpoint], **popen)
    replays: list[subprocess.Popen] = []
    try:
        _serving(router, "listening on")
        with open_client(endpoint) as session:
            for n, stop in enumerate(("sigterm", "message", "sigint")):
                replay = subprocess.Popen([sys.executable, "-m", "services.replay",
                                           "--data", str(tmp_path / f"run{n}")], **popen)
                replays.append(replay)
                _serving(replay, "serving run sig")
                if stop == "message":
                    session.put(wire.Keys("sig").stop, wire.encode(wire.Stop("run done")))
                else:
                    replay.send_signal(signal.SIGTERM if stop == "sigterm" else signal.SIGINT)
                rest = replay.communicate(timeout=60)[1]
                expected = {"sigterm": 128 + signal.SIGTERM, "message": 0, "sigint": 128 + signal.SIGINT}
                assert replay.returncode == expected[stop], rest
                assert "Traceback" not in rest, rest
        router.send_signal(signal.SIGTERM)
        assert router.wait(60) == 128 + signal.SIGTERM
    finally:
        for proc in (*replays, router):
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_a_second_evaluator_on_a_run_folder_is_refused(tmp_path):
    """Its pictures and media.json are one evaluator's: a second one would overwrite them."""
    from shared.zenoh_session import open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "NASA_ZENOH_CONNECT": endpoint, "NASA_RUN_ID": "two"}
    env.pop("NASA_ZENOH_AUTH", None)
    env.pop("NASA_PARENT_PID", None)
    with open_router(endpoint), faults.lock_service(tmp_path, "evaluator"):
        done = subprocess.run([sys.executable, "-m", "services.evaluator", "--data", str(tmp_path)],
                              capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and str(tmp_path) in done.stderr, done.stderr


# -- disk full -------------------------------------------------------------------------------


def _fill(disk: Path) -> Path:
    """A file taking every free byte of `disk`."""
    filler = disk / "filler"
    with contextlib.suppress(OSError), open(filler, "wb", buffering=0) as f:
        while True:
            f.write(b"\0" * 4096)
    return filler


def test_a_failed_log_write_leaves_no_torn_record(tmp_path):
    with tmpfs(tmp_path / "disk", "size=256k") as disk:
        writer = rlog.LogWriter(disk / "seg")
        writer.append(1, b"kept")
        _fill(disk)
        with pytest.raises(OSError):
            writer.append(1, b"x" * 200_000)
        assert (disk / "seg").stat().st_size == writer.bytes_written  # the partial record was cut
        (disk / "filler").unlink()
        writer.append(1, b"after")
        writer.close()
        assert [bytes(p) for _, p in rlog.read_segment(disk / "seg", is_last=True)] == [b"kept", b"after"]


def test_a_full_disk_pauses_inserts_unacknowledged_and_they_resume(tmp_path):
    with tmpfs(tmp_path / "disk", "size=4m") as disk:
        svc = make_service(disk, no_rate_limit=True, steps=10_000)
        stored = svc.insert_batch(batch(n=8)[0])
        filler = _fill(disk)
        result: list[int] = []
        more = batch(start=8, n=8, seed=1)[0]
        worker = threading.Thread(target=lambda: result.append(svc.insert_batch(more)))
        worker.start()
        deadline = time.monotonic() + 30
        while not svc.stats().write_error and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "No space" in svc.stats().write_error or "short write" in svc.stats().write_error
        assert worker.is_alive() and not result  # not stored, so never acknowledged: the thread waits
        filler.unlink()  # space returns
        worker.join(timeout=30)
        assert result == [8] and svc.stats().write_error == ""
        svc.store.close()
        again = open_store(svc.run_config, disk / "replay")
        assert again.num_inserted == stored + 8  # nothing torn, nothing lost
        again.close()


def test_a_snapshot_on_a_full_disk_is_reported_and_leaves_no_file(tmp_path):
    with tmpfs(tmp_path / "disk", "size=4m") as disk:
        svc = make_service(disk, no_rate_limit=True, steps=10_000)
        stored = svc.insert_batch(batch(n=8)[0])
        filler = _fill(disk)
        svc.store.snapshot(block=False)
        svc.store._snapshot_thread.join()
        assert svc.stats().write_error.startswith("snapshot: ")
        assert not list((disk / "replay").glob("*.tmp"))  # a half-written snapshot holds no space
        filler.unlink()
        assert svc.insert_batch(batch(start=8, n=8, seed=1)[0]) == 8
        svc.store.snapshot(block=False)
        svc.store._snapshot_thread.join()
        assert svc.stats().write_error == ""
        svc.store.close()
        again = open_store(svc.run_config, disk / "replay")
        assert again.num_inserted == stored + 8
        again.close()


# -- health and dead threads -----------------------------------------------------------------


def _learner(tmp_path) -> Learner:  # noqa: ANN001
    learner = Learner.__new__(Learner)
    learner.core = core_on(tmp_path)
    learner.args = LearnerArgs()
    learner.stop = StopFlag()
    return learner


def test_health_says_why_the_learner_is_not_healthy(tmp_path):
    learner = _learner(tmp_path)
    board = learner.core.board
    assert learner.health() == []
    board.seen_env_steps(100)
    board.last_update -= learner.args.stall_s + 1
    assert any("stalled" in r for r in learner.health())
    board.evaluating = True  # a long evaluation between updates is not a stall
    assert learner.health() == []
    board.evaluating = False
    seen: list = []
    learner.between = SimpleNamespace(run=lambda target: seen.append(board.evaluating) or "a result")
    learner._record_eval = lambda result, how="": seen.append(result)
    learner._evaluate(100)
    assert seen == [True, "a result"] and not board.evaluating and learner.health() == []
    board.last_update = time.monotonic()
    board.skipped_updates = learner.args.max_skipped_updates + 1
    board.replay_stats(wire.ReplayStats(1, 1, 100, 100, 0, 0, 0, False, "OSError: No space left on device"))
    learner.core.checkpoint_error = "OSError: read-only file system"
    for inc in range(1, 3 + learner.args.actor_restarts):
        board.actor_alive(7, inc, True)
    board.actor_alive(8, 1, True)
    reasons = learner.health()
    assert any("skipped" in r for r in reasons) and any("replay cannot write" in r for r in reasons)
    assert any("checkpoint" in r for r in reasons) and any("actor(s) [7]" in r for r in reasons)
    assert len(reasons) == 4


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_dead_prefetch_thread_is_noticed():
    class Broken:
        num_inserted = 0

        def sample(self, batch_size, wait_s):  # noqa: ANN001
            raise MemoryError("what nothing catches")

    with Prefetcher(Broken(), 4, 2, StopFlag()) as prefetcher:
        deadline = time.monotonic() + 10
        while len(prefetcher.dead()) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert prefetcher.dead() == ["prefetch0", "prefetch1"]


# -- the ratio across a learner restart ------------------------------------------------------


def test_a_starting_learner_sets_the_limiters_sample_count_to_its_updates(tmp_path):
    svc = make_service(tmp_path, warmup=4, steps=100)
    assert svc.insert_batch(batch(n=8)[0]) == 8  # within the limiter's window: none waits
    assert svc.limiter.take_sample(6, timeout=0)  # drawn by a learner that died before checkpointing them
    reply = svc.sample(wire.SampleRequest(1, 0.0, sync_samples=2))  # the restarted learner made 2
    assert reply.reason == "synced" and svc.limiter.stats()["samples"] == 2
    svc.sample(wire.SampleRequest(1, 0.0, sync_samples=50))  # never more than counted
    assert svc.limiter.stats()["samples"] == 2
    assert svc.sample(wire.SampleRequest(4, 0.0)).ok  # the lost samples are drawn again
    svc.store.close()


def test_an_actor_is_alive_only_with_its_token_and_restarts_count_once_each(tmp_path):
    board = _learner(tmp_path).core.board
    board.actor_status(wire.ActorStatus(5, 1, 10, 0, 0, 1.0, []))  # a heartbeat, no process seen
    assert board.snapshot()["actors"][0]["alive"] is False
    board.actor_alive(5, 1, True)
    assert board.snapshot()["actors"][0]["alive"] is True
    for inc in (2, 3):  # each restart's heartbeat may come before or after its token
        board.actor_status(wire.ActorStatus(5, inc, 10, 0, 0, 1.0, []))
        board.actor_alive(5, inc, True)
        board.actor_alive(5, inc, True)
    assert board.crash_looping(1, 60.0) == [5] and board.crash_looping(2, 60.0) == []


def test_the_status_board_shows_the_batches_the_replay_refused_each_actor() -> None:
    # An actor whose batches the replay refuses acts on until it stops: /status shows the count.
    from services.learner.status import StatusBoard

    board = StatusBoard()
    board.actor_alive(5, 1, True)
    board.actor_status(wire.ActorStatus(5, 1, 10, 0, 0, 1.0, [], refused=4))
    assert board.snapshot()["actors"][0]["refused"] == 4
    board.actor_status(wire.ActorStatus(5, 2, 10, 0, 0, 1.0, []))  # a new incarnation counts afresh
    assert board.snapshot()["actors"][0]["refused"] == 0
