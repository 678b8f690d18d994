"""`nasa up` as a user runs it: first line names the preset, `nasa status` reads it, Ctrl-C stops all,
and the same command again resumes the run."""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import stat
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from system_harness import REPO, TINY, WARMUP

from bench.up_profile import service_pids
from nasa import layout
from nasa.up import TEST_START_PAUSE, free_port
from shared.runlog import read_rows


def children_of(pid: int) -> list[int]:
    """Live processes started under launcher `pid`."""
    return list(service_pids(pid).values())


def niceness(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[16])


def environ_of(pid: int) -> dict[str, str]:
    pairs = Path(f"/proc/{pid}/environ").read_bytes().decode().split("\0")
    return dict(pair.split("=", 1) for pair in pairs if "=" in pair)


@contextlib.contextmanager
def nasa_up(data: Path, env: dict[str, str] | None = None) -> Iterator[tuple[subprocess.Popen, int]]:
    """`nasa up` on `data` as a user starts it (`env` over this process's); killed if still running,
    and nothing left after."""
    port = free_port()
    cmd = [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--actors", "1",
           "--steps", "100000", "--device", "cpu", "--data", str(data), "--port", str(port),
           "--router-port", "0", "--learner-threads", "1", "--logs", "--", *TINY]
    up = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})})
    try:
        yield up, port
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert children_of(up.pid) == []


def wait_status(up: subprocess.Popen, port: int, pred, what: str, timeout: float = 150) -> dict:
    deadline = time.monotonic() + timeout
    status = None
    url = f"http://127.0.0.1:{port}/status"
    while time.monotonic() < deadline and up.poll() is None:
        out = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--url", url],
                             cwd=REPO, capture_output=True, text=True)
        if out.returncode == 0:
            status = json.loads(out.stdout)
            if pred(status):
                return status
        time.sleep(0.5)
    raise AssertionError(f"timed out waiting for {what}; last status {status}")


def stop_with_ctrl_c(up: subprocess.Popen) -> None:
    services = service_pids(up.pid)
    kids = list(services.values())
    assert len(kids) == 4  # replay, learner, evaluator, one actor
    # On a small machine the evaluator runs at a low CPU priority, and only the evaluator.
    expected = layout.choose(layout.usable_cores(), gpu=False).evaluator_nice
    nice = {name: niceness(p) for name, p in services.items()}
    assert nice == {"evaluator": expected, "replay": 0, "learner": 0, "actor": 0}, nice
    # Each service's OpenMP wait policy as the layout chose it (none set by the user here).
    lay = layout.choose(layout.usable_cores(), gpu=False, actors=1, learner_threads=1)
    if "OMP_WAIT_POLICY" not in os.environ:
        policy = {name: environ_of(p).get("OMP_WAIT_POLICY") for name, p in services.items()}
        assert policy == {name: lay.omp_env(name).get("OMP_WAIT_POLICY") for name in services}, policy
    up.send_signal(signal.SIGINT)
    rest, _ = up.communicate(timeout=90)
    assert up.returncode == 128 + signal.SIGINT, rest  # 130, as `nasa train`: stopped, not finished
    assert "nasa up: stopped" in rest
    assert [p for p in kids if Path(f"/proc/{p}").exists() and p in children_of(up.pid)] == []


@pytest.mark.timeout(360)
def test_nasa_up_runs_reports_stops_on_ctrl_c_and_resumes(tmp_path):
    data = tmp_path / "run"
    with nasa_up(data) as (up, port):
        first = up.stdout.readline()
        assert first.startswith("nasa up: preset cpu-small (auto: no GPU"), first
        chosen = up.stdout.readline()  # the layout: the flags' values kept, the rest from the machine
        assert "1 actor(s), learner 1 torch thread(s)" in chosen and "evaluator own process" in chosen, chosen
        # Logins on by default: the run's own credentials, readable by its owner only.
        assert f"Zenoh logins and access control from {data / 'auth'}" in up.stdout.readline()
        assert f"http://127.0.0.1:{port}/status" in up.stdout.readline()
        status = wait_status(up, port, lambda s: s["actors"] and s["updates"] > 0, "actors and updates")
        assert status["task"] == "cartpole-balance" and status["algo"] == "nasa_td3"
        assert not status["resumed"]
        assert stat.S_IMODE((data / "auth" / "users.txt").stat().st_mode) == 0o600
        # One actor on a CPU runs at most one env step ahead of the learner's schedule (the
        # limiter's inserts over its samples, past the warm-up), so it acts with fresh weights.
        later = wait_status(up, port, lambda s: s["updates"] > 50, "50 updates")
        replay = later["replay"]
        assert replay["limiter_inserts"] - replay["limiter_samples"] <= WARMUP + 2, replay
        stop_with_ctrl_c(up)
    assert (data / "replay" / "MANIFEST.json").exists() and (data / "learner" / "checkpoint.pt").exists()

    # Stopped, the run still answers `nasa status --data` with the learner's last status.
    dead = f"http://127.0.0.1:{port}/status"
    last = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--url", dead, "--data", str(data)],
                          cwd=REPO, capture_output=True, text=True)
    assert last.returncode == 0, last.stderr
    assert "not running" in last.stderr
    last_status = json.loads(last.stdout)
    assert last_status["run_id"] == status["run_id"] and last_status["updates"] >= status["updates"]
    missing = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--url", dead, "--data",
                              str(tmp_path / "nowhere")], cwd=REPO, capture_output=True, text=True)
    assert missing.returncode == 1 and "no " in missing.stderr

    # The same command again continues the run: the learner from its checkpoint, the
    # replay from its log.
    saved = torch.load(data / "learner" / "checkpoint.pt", weights_only=True)
    with nasa_up(data) as (again, port):
        resumed = wait_status(
            again, port, lambda s: s["resumed"] and s["replay"]["size"] > 0, "a resumed run"
        )
        assert resumed["updates"] >= saved["agent"]["num_updates"] > 0
        assert resumed["replay"]["size"] >= status["replay"]["size"]
        wait_status(again, port, lambda s: s["updates"] > resumed["updates"], "learning to go on")
        stop_with_ctrl_c(again)


@pytest.mark.timeout(420)
def test_a_second_ctrl_c_kills_the_services_left_and_the_same_command_resumes_the_run(tmp_path):
    data = tmp_path / "run"
    with nasa_up(data) as (up, port):
        wait_status(up, port, lambda s: s["actors"] and s["updates"] > 0, "actors and updates")
        replay = service_pids(up.pid)["replay"]
        os.kill(replay, signal.SIGSTOP)  # it cannot stop in order now: the stop would wait 20 s for it
        up.send_signal(signal.SIGINT)
        line = next(line for line in up.stdout if line.startswith("nasa up: stopping in order"))
        assert line.strip() == "nasa up: stopping in order (SIGINT); Ctrl-C again kills what is left"
        up.send_signal(signal.SIGINT)
        rest, _ = up.communicate(timeout=90)
    assert up.returncode == 130, rest
    forced = rest.strip().splitlines()[-1]
    assert forced.startswith("nasa up: forced to stop (SIGINT); killed ") and "replay" in forced, rest
    assert forced.endswith(f"; the same command resumes the run from {data}"), rest
    assert "did not stop within" not in rest, rest  # forced, not waited out
    assert not Path(f"/proc/{replay}").exists()
    # Killed mid-stop, the run folder is whole: the replay reopens its log, the learner goes on.
    with nasa_up(data) as (again, port):
        wait_status(again, port, lambda s: s["replay"]["size"] > 0 and s["updates"] > 0, "the run going on")
        again.send_signal(signal.SIGINT)
        out, _ = again.communicate(timeout=90)
    assert again.returncode == 130 and "nasa up: stopped" in out, out


@pytest.mark.timeout(240)
def test_a_ctrl_c_while_nasa_up_starts_its_services_starts_no_more_and_stops_those_started(tmp_path):
    # Start-up held after each service (a test-only hook): the Ctrl-C lands after the replay started
    # and before the learner did.
    data = tmp_path / "run"
    with nasa_up(data, env={TEST_START_PAUSE: "600"}) as (up, _port):
        deadline = time.monotonic() + 150
        while "replay" not in service_pids(up.pid):
            assert time.monotonic() < deadline and up.poll() is None, up.stdout.read() if up.poll() else ""
            time.sleep(0.1)
        replay = service_pids(up.pid)["replay"]
        up.send_signal(signal.SIGINT)
        out, _ = up.communicate(timeout=120)
    assert up.returncode == 130, out
    lines = out.strip().splitlines()
    assert lines[-3:] == [
        "nasa up: SIGINT while starting the services: learner, evaluator, actor-0 not started",
        "nasa up: stopping in order (SIGINT); Ctrl-C again kills what is left",
        "nasa up: stopped",
    ], out
    assert "/status" not in out and "Traceback" not in out, out
    assert sorted(p.name for p in (data / "logs").iterdir()) == ["replay.log"]
    assert not Path(f"/proc/{replay}").exists()


# A launcher (a benchmark, say) that starts `nasa up` naming itself in NASA_PARENT_PID, writes
# nasa up's output to a file, and waits.
LAUNCHER = """
import os, subprocess, sys, time
env = {**os.environ, "NASA_PARENT_PID": str(os.getpid())}
with open(sys.argv[1], "w") as log:
    subprocess.Popen(sys.argv[2:], env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
time.sleep(600)
"""


@pytest.mark.timeout(240)
def test_nasa_up_stops_its_services_in_order_when_its_launcher_is_killed(tmp_path):
    # The launcher dies by SIGKILL, which it cannot pass on: nasa up gets SIGTERM (PR_SET_PDEATHSIG)
    # and stops as on a Ctrl-C. Start-up is held after the replay (a test-only hook), so one
    # service runs when it dies.
    from bench.processes import processes_with

    data, log, mark = tmp_path / "run", tmp_path / "up.log", uuid.uuid4().hex
    cmd = [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--actors", "1",
           "--steps", "100000", "--device", "cpu", "--data", str(data), "--port", str(free_port()),
           "--router-port", "0", "--learner-threads", "1", "--logs", "--", *TINY]
    env = {**os.environ, "PYTHONPATH": str(REPO), "NASA_TEST_UP_MARK": mark, TEST_START_PAUSE: "600"}
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(log), *cmd], cwd=REPO, env=env)

    def marked() -> list[tuple[int, list[str]]]:
        return [p for p in processes_with("NASA_TEST_UP_MARK", mark) if p[0] != launcher.pid]

    try:
        replay_log = data / "logs" / "replay.log"
        deadline = time.monotonic() + 150
        while "serving run" not in (replay_log.read_text() if replay_log.exists() else ""):
            assert time.monotonic() < deadline and launcher.poll() is None, log.read_text()
            time.sleep(0.1)
        assert any("services.replay" in argv for _, argv in marked())
        launcher.kill()
        launcher.wait()
        deadline = time.monotonic() + 90
        while (left := marked()) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert left == [], f"left running: {left}\n{log.read_text()}"
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        for pid, _ in marked():  # not to leave them to the rest of the suite
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    lines = log.read_text().strip().splitlines()
    assert lines[-3:] == [
        "nasa up: SIGTERM while starting the services: learner, evaluator, actor-0 not started",
        "nasa up: stopping in order (SIGTERM); Ctrl-C again kills what is left",
        "nasa up: stopped",
    ], lines
    assert "stopping" in replay_log.read_text().split("serving run")[-1]


@pytest.mark.timeout(180)
def test_nasa_up_ends_with_a_clear_error_on_a_checkpoint_it_cannot_continue(tmp_path):
    # The learner refuses the checkpoint (exit 2); restarting it would only fail again,
    # so `nasa up` stops everything, says why, and exits 2 with the checkpoint untouched.
    data = tmp_path / "run"
    (data / "learner").mkdir(parents=True)
    torch.save({"format": 1, "updates": 10}, data / "learner" / "checkpoint.pt")
    before = (data / "learner" / "checkpoint.pt").read_bytes()
    with nasa_up(data) as (up, _port):
        out, _ = up.communicate(timeout=150)
    assert up.returncode == 2, out
    assert "learner refused its input" in out and "has format 1" in out, out
    assert "restarting" not in out
    assert "nasa up: stopped" in out
    assert (data / "learner" / "checkpoint.pt").read_bytes() == before


def _controlling_terminal() -> None:
    import fcntl
    import termios

    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


@pytest.mark.timeout(240)
def test_nasa_up_stops_every_service_in_order_when_its_terminal_closes(tmp_path):
    # An ssh session that drops: the kernel sends SIGHUP, and writes to the terminal fail from
    # then on. `nasa up` stops as for SIGTERM (its services in order, none left) and exits 129.
    data = tmp_path / "run"
    master, terminal = os.openpty()
    cmd = [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--actors", "1",
           "--steps", "100000", "--device", "cpu", "--data", str(data), "--port", str(free_port()),
           "--router-port", "0", "--learner-threads", "1", "--logs", "--", *TINY]
    up = subprocess.Popen(cmd, cwd=REPO, stdin=terminal, stdout=terminal, stderr=terminal,
                          start_new_session=True, preexec_fn=_controlling_terminal,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    os.close(terminal)
    try:
        seen = b""
        deadline = time.monotonic() + 150
        started = {"replay": "serving run", "learner": "status on http", "actor-0": "acting on",
                   "evaluator": "evaluating every"}  # each has its stop handler by then

        def log(service: str) -> str:
            path = data / "logs" / f"{service}.log"
            return path.read_text() if path.exists() else ""

        while not all(line in log(service) for service, line in started.items()):
            assert time.monotonic() < deadline and up.poll() is None, seen.decode()
            readable, _, _ = select.select([master], [], [], 0.5)
            if readable:
                try:
                    seen += os.read(master, 4096)
                except OSError:  # no process has the terminal open: nasa up ended
                    raise AssertionError(f"nasa up ended ({up.wait()}): {seen.decode()}") from None
        os.close(master)  # the terminal hangs up
        master = -1
        assert up.wait(timeout=150) == 128 + signal.SIGHUP
        assert children_of(up.pid) == []
        assert b"/status" in seen
        for service in started:
            assert "stopping" in log(service).split(started[service])[-1], service
    finally:
        if master >= 0:
            os.close(master)
        if up.poll() is None:
            up.kill()
            up.wait()


@pytest.mark.timeout(180)
@pytest.mark.parametrize(("signum", "said"), [(signal.SIGINT, "interrupted"),
                                              (signal.SIGTERM, "stopped (SIGTERM)")])
def test_nasa_up_waits_for_an_earlier_launchs_service_and_ctrl_c_there_is_one_line(tmp_path, signum, said):
    # The evaluator of a `nasa up` killed with SIGKILL still holds its role's lock while it stops:
    # the same command again says it waits for it; Ctrl-C then ends it with one line and 130.
    from tests.test_hardening_faults import ROLE_HOLD

    data = tmp_path / "run"
    data.mkdir()
    orphan = subprocess.Popen([sys.executable, "-c", ROLE_HOLD, str(data)], stdout=subprocess.PIPE,
                              text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert orphan.stdout.readline().strip() == "locked"
        with nasa_up(data) as (up, _port):
            first = up.stdout.readline()
            assert first.startswith("nasa up: the evaluator of an earlier launch on"), first
            assert f"(pid {orphan.pid} " in first and "waiting up to 60 s for it to exit" in first, first
            up.send_signal(signum)
            rest, _ = up.communicate(timeout=60)
        assert up.returncode == 128 + signum, rest
        assert rest.strip() == f"nasa up: {said} before any service started", rest
        assert orphan.poll() is None
    finally:
        orphan.kill()
        orphan.wait()


def test_nasa_up_rejects_an_unknown_task_before_starting_anything(tmp_path):
    data = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-juggle", "--data", str(data),
         "--router-port", "0", "--port", str(free_port())],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2, result.stderr
    assert "nasa up: error: unknown task 'cartpole-juggle'; valid tasks are" in result.stderr
    assert "Traceback" not in result.stderr
    assert not data.exists()  # no service was started


def test_nasa_up_refuses_to_resume_a_run_with_other_settings_before_starting_anything(tmp_path):
    # The run folder of an earlier `nasa up --image-size 32`; this one asks for 48.
    from nasa.up import parse_up, prepare

    data = tmp_path / "run"
    first, _ = parse_up(["--task", "cartpole-balance", "--image-size", "32", "--data", str(data)])
    prepare(first, data)
    before = (data / "config.json").read_bytes()
    result = subprocess.run(
        [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--image-size", "48",
         "--data", str(data), "--router-port", "0", "--port", str(free_port()), "--logs"],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2, result.stderr
    assert "nasa up: error: settings differ from the run's" in result.stderr
    assert "env.image_size (48 here, 32 in the run)" in result.stderr
    assert "Traceback" not in result.stderr and result.stdout == ""  # nothing started
    assert sorted(p.name for p in data.iterdir() if p.name != ".lock") == ["config.json"]  # .lock: its lock
    assert (data / "config.json").read_bytes() == before


@pytest.mark.timeout(300)
def test_nasa_up_can_evaluate_between_the_learners_updates_with_no_evaluator_process(tmp_path):
    # A whole short run: the learner plays each evaluation itself (step 0 with its initial
    # weights, then each multiple of --eval-every, the last one before the run ends).
    data = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--steps", "150",
         "--device", "cpu", "--data", str(data), "--port", str(free_port()), "--router-port", "0",
         "--logs", "--evaluate-in", "learner", "--eval-every", "50", "--eval-episodes", "2", *TINY],
        cwd=REPO, capture_output=True, text=True, timeout=240, env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "evaluator between the learner's updates" in result.stdout
    assert sorted(p.name for p in (data / "logs").iterdir()) == ["actor-0.log", "learner.log", "replay.log"]
    rows = (data / "eval.csv").read_text().splitlines()
    steps = [int(r.split(",")[0]) for r in rows[1:]]
    # A step the actor passed while the learner was evaluating is skipped, as the evaluator skips it.
    assert steps[0] == 0 and steps[-1] == 150 and steps == sorted(set(steps)), rows
    assert set(steps) <= {0, 50, 100, 150}, rows
    last = read_rows(data / "eval.csv")[-1]
    assert int(last["updates"]) == 150 - WARMUP  # the budget's step: the final policy's
    learner_log = (data / "logs" / "learner.log").read_text()
    assert "eval step 0 (policy 0, between updates)" in learner_log
    assert "eval step 150 (policy " in learner_log and "run done" in learner_log
