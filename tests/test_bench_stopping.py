"""A benchmark stopped by Ctrl-C or SIGTERM leaves no process and no temporary folder behind.

Each benchmark runs as a user starts it (`python -m bench.<name>`, tiny settings) with a mark in
its environment that every process it starts inherits, whatever session it runs in: what carries
the mark once the benchmark has exited was left behind.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from system_harness import REPO, TINY

from bench.processes import processes_with, stop_group

pytestmark = pytest.mark.system


def marked(mark: str) -> list[tuple[int, str]]:
    """Live processes (pid, command line) whose environment holds BENCH_TEST_MARK=`mark`."""
    return [(pid, " ".join(argv)) for pid, argv in processes_with("BENCH_TEST_MARK", mark)]


def wait_for(what: str, ready: Callable[[], bool], bench: subprocess.Popen, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        if bench.poll() is not None:
            pytest.fail(f"the benchmark ended (exit {bench.returncode}) before {what}: {bench.stdout.read()}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} in {timeout:.0f} s")
        time.sleep(0.5)


def stop_and_check(bench: subprocess.Popen, signum: int, mark: str, tmp: Path) -> str:
    """Send `signum` to the benchmark; it exits 128 + signum, and nothing of it is left."""
    bench.send_signal(signum)
    try:
        out, _ = bench.communicate(timeout=150)
    except subprocess.TimeoutExpired:
        bench.kill()
        pytest.fail("the benchmark did not stop within 150 s of the signal")
    deadline = time.monotonic() + 20  # children stopping on their own after it (PDEATHSIG)
    while (left := marked(mark)) and time.monotonic() < deadline:
        time.sleep(0.5)
    for pid, _ in left:  # not to leave them to the rest of the suite
        os.kill(pid, signal.SIGKILL)
    assert left == [], f"left running: {left}\n{out}"
    # torch's compile cache is torch's, kept on purpose
    left_files = sorted(p.name for p in tmp.iterdir() if not p.name.startswith("torchinductor_"))
    assert left_files == [], "temporary folders left behind"
    assert bench.returncode == 128 + signum, out
    assert "Traceback" not in out, out
    return out


_started: list[tuple[subprocess.Popen, str]] = []  # the benchmarks the running test started, and their marks


@pytest.fixture(autouse=True)
def no_benchmark_left() -> Iterator[None]:
    """Kill what a failing test leaves of its benchmarks: one that never got to its signal runs on for
    its whole budget (minutes of a training run), beside the rest of the suite."""
    yield
    while _started:
        bench, mark = _started.pop()
        if bench.poll() is None:
            bench.kill()
            bench.wait()
        for pid, _ in marked(mark):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def start(argv: list[str], mark: str, tmp: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO), "BENCH_TEST_MARK": mark, "TMPDIR": str(tmp)}
    bench = subprocess.Popen([sys.executable, "-m", *argv], cwd=REPO, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    _started.append((bench, mark))
    return bench


def running(mark: str, needle: str) -> Callable[[], bool]:
    return lambda: any(needle in cmd for _, cmd in marked(mark))


def gone(pid: int) -> bool:
    """Exited (a zombie counts: its parent has yet to reap it)."""
    try:
        return Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[0] == b"Z"
    except FileNotFoundError:
        return True


def wait_gone(pid: int, deadline_s: float = 60.0) -> None:
    """Wait for `pid` to exit; the deadline only stops a hung test."""
    end = time.monotonic() + deadline_s
    while not gone(pid):
        assert time.monotonic() < end, f"process {pid} still running"
        time.sleep(0.05)


def test_processes_with_reads_processes_whose_name_argv_and_environment_are_not_utf8(tmp_path):
    # It scans every process of the machine: one with odd bytes must not end the scan.
    mark = uuid.uuid4().hex
    odd_name = os.path.join(os.fsencode(tmp_path), b"py\xff")  # the process's name, in /proc/PID/stat
    os.symlink(os.fsencode(os.path.realpath(sys.executable)), odd_name)
    env = {"BENCH_TEST_MARK": mark, "ODD": b"\xfe\xfd"}
    child = subprocess.Popen([odd_name, "-c", "import time; time.sleep(600)", b"arg\xfc"], env=env)
    try:
        end = time.monotonic() + 60  # until it runs python: before, it is a copy of this process
        while not (found := processes_with("BENCH_TEST_MARK", mark)):
            assert time.monotonic() < end, "the child never showed up"
            time.sleep(0.05)
        [(pid, argv)] = found
        assert pid == child.pid and argv[1:4] == ["-c", "import time; time.sleep(600)", "arg\ufffd"]
    finally:
        child.kill()
        child.wait()


# A member of the leader's group that ignores SIGINT and stops on SIGTERM, saying so in a file.
MEMBER = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
    "def stopped(*_):\n"
    "    open(sys.argv[1], 'w').write('SIGTERM')\n"
    "    sys.exit(0)\n"
    "signal.signal(signal.SIGTERM, stopped)\n"
    "print('up', flush=True)\n"
    "time.sleep(600)\n"
)
# The leader: starts the member, prints its pid, then exits at once or waits for SIGINT.
LEADER = (
    "import subprocess, sys, time\n"
    "member = subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], stdout=subprocess.PIPE)\n"
    "assert member.stdout.readline() == b'up\\n'\n"
    "print(member.pid, flush=True)\n"
    "if sys.argv[3] == 'wait':\n"
    "    time.sleep(600)\n"
)


def start_group(tmp_path: Path, then: str) -> tuple[subprocess.Popen, int]:
    leader = subprocess.Popen([sys.executable, "-c", LEADER, MEMBER, str(tmp_path / "member"), then],
                              stdout=subprocess.PIPE, text=True, start_new_session=True)
    return leader, int(leader.stdout.readline())


def test_stop_group_stops_the_members_a_leader_that_exited_left_behind(tmp_path):
    leader, member = start_group(tmp_path, "exit")
    try:
        assert leader.wait(timeout=120) == 0  # exited by itself, its member still running
        assert not gone(member)
        stop_group(leader, ((signal.SIGINT, 0.5), (signal.SIGTERM, 60.0)))  # the member ignores SIGINT
        wait_gone(member)
        assert (tmp_path / "member").read_text() == "SIGTERM"  # stopped, not killed, as it asks
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(member, signal.SIGKILL)


def test_stop_group_goes_on_with_the_members_a_leader_stopped_by_its_first_signal_left(tmp_path):
    leader, member = start_group(tmp_path, "wait")
    try:
        # The leader ends on SIGINT within its grace; the member, ignoring it, waits out the rest.
        assert stop_group(leader, ((signal.SIGINT, 5.0), (signal.SIGTERM, 60.0))) != 0
        wait_gone(member)
        assert (tmp_path / "member").read_text() == "SIGTERM"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(member, signal.SIGKILL)


@pytest.mark.timeout(60)  # only stops a hung test: the grace below is far longer
def test_stop_group_takes_a_group_left_with_only_zombies_for_stopped():
    """A member that exited but is not reaped stays in its group as a zombie; one whose parent
    never reaps it (an orphan where a container's first process reaps nothing) stays for ever, and
    stop_group waited out its whole grace on it. Here the member is this test's own child, which
    it does not reap until the end."""
    sleep = [sys.executable, "-c", "import time; time.sleep(600)"]
    leader = subprocess.Popen(sleep, process_group=0)
    member = subprocess.Popen(sleep, process_group=leader.pid)
    try:
        stop_group(leader, ((signal.SIGTERM, 3600.0),))
        assert gone(member.pid) and member.returncode is None  # a zombie, still in the group
    finally:
        member.kill()
        member.wait()
        leader.kill()
        leader.wait()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_bench_learning_stops_its_run_on_a_signal(tmp_path, signum):
    # nasa train runs in a session of its own: no signal to the benchmark reaches it but through it.
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    bench = start(["bench.learning", "--only", "train", "--task", "cartpole-balance", "--minutes", "10",
                   "--out", str(tmp_path / "out"), "--", *TINY], mark, tmp)
    wait_for("nasa train", running(mark, "nasa.cli train"), bench)
    time.sleep(1.0)
    stop_and_check(bench, signum, mark, tmp)


def killed_leaves_nothing(bench: subprocess.Popen, mark: str) -> None:
    """SIGKILL the benchmark: it runs no `finally` block, so what it started must follow its death
    itself (NASA_PARENT_PID); nothing carrying its mark may be left once that has stopped."""
    bench.kill()
    bench.communicate()
    deadline = time.monotonic() + 90  # nasa up stopping its services in order
    while (left := marked(mark)) and time.monotonic() < deadline:
        time.sleep(0.5)
    for pid, _ in left:  # not to leave them to the rest of the suite
        os.kill(pid, signal.SIGKILL)
    assert left == [], f"left running: {left}"


@pytest.mark.parametrize("runner", ["train", "up"])
def test_bench_learning_killed_by_sigkill_leaves_no_process_of_its_run(tmp_path, runner):
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out"
    bench = start(["bench.learning", "--only", runner, "--task", "cartpole-balance", "--minutes", "10",
                   "--out", str(out), "--", *TINY], mark, tmp)
    if runner == "train":  # its run folder made: nasa train is past its start
        config = out / "cartpole-balance" / "nasa_td3" / "seed0" / "config.json"
        wait_for("nasa train's run folder", config.exists, bench)
    else:
        wait_for("replay service", running(mark, "services.replay"), bench)
    killed_leaves_nothing(bench, mark)


def up_profile_running(tmp_path: Path) -> tuple[subprocess.Popen, str, Path]:
    """bench.up_profile on a tiny run, once its nasa up has started the replay."""
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    bench = start(["bench.up_profile", "--task", "cartpole-balance", "--seconds", "600", "--",
                   "--actors", "1", "--learner-threads", "1", "--", *TINY], mark, tmp)
    wait_for("replay service", running(mark, "services.replay"), bench)
    return bench, mark, tmp


def test_bench_up_profile_stops_nasa_up_on_sigterm(tmp_path):
    bench, mark, tmp = up_profile_running(tmp_path)
    stop_and_check(bench, signal.SIGTERM, mark, tmp)


def test_bench_up_profile_killed_by_sigkill_leaves_no_process_of_its_run(tmp_path):
    bench, mark, _ = up_profile_running(tmp_path)
    killed_leaves_nothing(bench, mark)


def test_bench_system_removes_its_folders_on_sigterm(tmp_path):
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    bench = start(["bench.system", "--seconds", "2", "--fill", "50"], mark, tmp)
    wait_for("a service", running(mark, "services."), bench)
    stop_and_check(bench, signal.SIGTERM, mark, tmp)


def test_bench_learner_stops_its_worker_and_removes_its_batch_on_sigterm(tmp_path):
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    bench = start(["bench.learner", "--rounds", "1", "--batch", "8", "--updates", "2000", "--threads", "1"],
                  mark, tmp)
    wait_for("worker", running(mark, "--worker"), bench)
    stop_and_check(bench, signal.SIGTERM, mark, tmp)


def test_bench_status_polling_stops_its_pollers_on_sigterm(tmp_path):
    mark, tmp = uuid.uuid4().hex, tmp_path / "tmp"
    tmp.mkdir()
    bench = start(["bench.status_polling", "--pollers", "2", "--seconds", "8", "--rounds", "1"], mark, tmp)
    # The quiet window comes first: wait for the pollers of the next one, in its measured part.
    wait_for("pollers", lambda: sum("httpx" in cmd for _, cmd in marked(mark)) == 2, bench)
    time.sleep(1.5)
    stop_and_check(bench, signal.SIGTERM, mark, tmp)
