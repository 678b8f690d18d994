"""How the `nasa` commands stop: a second Ctrl-C forces the stop, a Ctrl-C during start-up is one
line, with real processes and real signals (no Zenoh, no torch in the children)."""

from __future__ import annotations

import ast
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}

# nasa up's StopSignals over a Supervisor whose two services ignore SIGTERM: the stop in order
# would wait 600 s for each. argv: the folder, and `signal` (a Ctrl-C starts the stop) or `done`
# (the run ends by itself and stops in order).
UP_STOP = """
import pathlib, sys, time
from nasa.up import StopSignals, Supervisor, say
folder, how = pathlib.Path(sys.argv[1]), sys.argv[2]
child = '''
import pathlib, signal, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
(pathlib.Path(sys.argv[2]) / ("ready-" + sys.argv[1])).touch()
while True:
    time.sleep(0.05)
'''
sup = Supervisor({}, folder / "logs", command=lambda role: [sys.executable, "-c", child, role])
stop = StopSignals(sup, "the same command resumes it")
stop.install()
for role in ("actor", "learner"):
    sup.add({"actor": "actor-0"}.get(role, role), role, [str(folder)])
while not all((folder / ("ready-" + r)).exists() for r in ("actor", "learner")):
    time.sleep(0.02)
print("pids", *[c.proc.pid for c in sup.children.values()], flush=True)
if how == "done":
    stop.reason = "the run is done (learner finished)"
while not stop.reason:
    time.sleep(0.05)
stop.stopping()
sup.stop_all(timeout_s=600, on_event=say)
say("stopped")
"""


def start(script: str, *args: str, env: dict | None = None, new_session: bool = False) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", script, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO, env=env or ENV,
                            start_new_session=new_session)


def gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] == "Z"  # a zombie is gone too
    except FileNotFoundError:
        return True


@contextlib.contextmanager
def up_stop(folder: Path, how: str) -> Iterator[tuple[subprocess.Popen, list[int]]]:
    """UP_STOP started, and its services' pids once both run. Its services ignore SIGTERM and run in
    sessions of their own: whatever of them a failing test leaves is killed here, not left running."""
    up = start(UP_STOP, str(folder), how)
    pids: list[int] = []
    try:
        pids += [int(p) for p in up.stdout.readline().split()[1:]]
        yield up, pids
    finally:
        up.kill()
        up.wait()
        for pid in pids:
            if not gone(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)


def test_a_second_ctrl_c_while_nasa_up_stops_in_order_kills_what_is_left_and_exits_130(tmp_path):
    with up_stop(tmp_path, "signal") as (up, pids):
        assert len(pids) == 2
        up.send_signal(signal.SIGINT)
        assert up.stdout.readline().strip() == ("nasa up: stopping in order (SIGINT); Ctrl-C again "
                                                "kills what is left")
        up.send_signal(signal.SIGINT)  # both services ignore SIGTERM: without it, a 600 s wait
        out, err = up.communicate(timeout=120)
        assert all(gone(p) for p in pids)
    assert up.returncode == 130, (out, err)
    assert out.strip() == ("nasa up: forced to stop (SIGINT); killed actor-0, learner; the same command "
                           "resumes it")
    assert "Traceback" not in err, err


def test_a_ctrl_c_while_a_finished_run_stops_in_order_forces_it(tmp_path):
    with up_stop(tmp_path, "done") as (up, pids):
        assert up.stdout.readline().strip() == ("nasa up: stopping in order (the run is done (learner "
                                                "finished)); Ctrl-C kills what is left")
        up.send_signal(signal.SIGTERM)
        out, _ = up.communicate(timeout=120)
        assert all(gone(p) for p in pids)
    assert up.returncode == 143, out
    assert out.strip().startswith("nasa up: forced to stop (SIGTERM); killed actor-0, learner")


def test_a_second_sighup_does_not_force_the_stop(tmp_path):
    # A closed terminal can send SIGHUP twice (the kernel, then the shell): it still stops in order.
    with up_stop(tmp_path, "signal") as (up, _):
        up.send_signal(signal.SIGHUP)
        assert up.stdout.readline().startswith("nasa up: stopping in order (SIGHUP)")
        up.send_signal(signal.SIGHUP)
        up.send_signal(signal.SIGINT)  # only this one forces: the exit code says which
        out, _ = up.communicate(timeout=120)
    assert up.returncode == 130 and out.startswith("nasa up: forced to stop (SIGINT)"), out


# nasa train's stop (nasa.cli.run_until_stopped) around a trainer whose closing hangs (a slow disk).
TRAIN_STOP = """
import sys, time
from pathlib import Path
from types import SimpleNamespace
from nasa.cli import run_until_stopped

class Trainer:
    counters, last_checkpoint_step = SimpleNamespace(env_steps=7), 5
    def run(self):
        print("running", flush=True)
        time.sleep(600)
    def close(self):
        print("closing", flush=True)
        time.sleep(600)

run_until_stopped(Trainer(), Path(sys.argv[1]))
"""


@pytest.mark.parametrize("launched", [False, True])
def test_a_second_ctrl_c_while_nasa_train_closes_its_files_stops_it_at_once(tmp_path, launched):
    # Under `nasa reproduce` (NASA_PARENT_PID), its SIGTERM follows the Ctrl-C both got: not a second
    # signal; the terminal's second Ctrl-C still forces.
    env = {**ENV, "NASA_PARENT_PID": str(os.getpid())} if launched else ENV
    train = start(TRAIN_STOP, str(tmp_path / "run"), env=env)
    try:
        assert train.stdout.readline() == "running\n"
        train.send_signal(signal.SIGINT)
        assert train.stdout.readline() == "closing\n"
        if launched:
            train.send_signal(signal.SIGTERM)
        train.send_signal(signal.SIGINT)
        _, err = train.communicate(timeout=120)
    finally:
        train.kill()
    assert train.returncode == 130, err
    lines = err.strip().splitlines()
    assert lines == [
        "nasa train: stopping at step 7: closing the run's files (Ctrl-C again to stop at once)",
        f"nasa train: forced to stop (SIGINT); its last checkpoint holds step 5; continue with: "
        f"nasa train --resume {tmp_path / 'run'}",
    ], err


def test_a_sigterm_while_nasa_train_closes_stops_it_at_once_under_a_launcher_in_another_session(tmp_path):
    # bench.learning starts nasa train in a session of its own, naming itself in NASA_PARENT_PID so
    # the run follows its death: no Ctrl-C reaches both, and its SIGTERM after a SIGINT that was not
    # enough must end the stop, as it would without a launcher.
    env = {**ENV, "NASA_PARENT_PID": str(os.getpid())}
    train = start(TRAIN_STOP, str(tmp_path / "run"), env=env, new_session=True)
    try:
        assert train.stdout.readline() == "running\n"
        train.send_signal(signal.SIGINT)
        assert train.stdout.readline() == "closing\n"
        train.send_signal(signal.SIGTERM)
        try:
            _, err = train.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            pytest.fail("the SIGTERM did not end nasa train's stop")
    finally:
        train.kill()
    assert train.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines() == [
        "nasa train: stopping at step 7: closing the run's files (Ctrl-C again to stop at once)",
        f"nasa train: forced to stop (SIGTERM); its last checkpoint holds step 5; continue with: "
        f"nasa train --resume {tmp_path / 'run'}",
    ], err


# A Ctrl-C at a given import (a real SIGINT to itself, from an import hook), then the command.
INTERRUPT_AT_IMPORT = """
import os, runpy, signal, sys
module, at, signum = sys.argv[1], sys.argv[2], getattr(signal, sys.argv[3])
class Hook:
    def find_spec(self, name, path, target=None):
        if name == at:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signum)
        return None
sys.meta_path.insert(0, Hook())
sys.argv = ["nasa", *sys.argv[4:]]
if module == "script":  # what the installed `nasa` script runs
    from nasa.cli import main
    sys.exit(main())
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(("module", "at", "argv", "line"), [
    ("script", "tyro", ["train", "--help"], "nasa: interrupted while starting"),
    ("nasa", "torch", ["plot", "--help"], "nasa: interrupted while starting"),
    ("nasa.cli", "shared.config", ["up", "--help"], "nasa: interrupted while starting"),
    # after the imports, inside a command before it has a stop of its own
    ("nasa.cli", "nasa.train", ["train", "--task", "cartpole-balance", "--out", "OUT"],
     "nasa train: interrupted"),
])
def test_a_ctrl_c_while_a_command_starts_is_one_line_and_130(tmp_path, module, at, argv, line):
    argv = [str(tmp_path / "run") if a == "OUT" else a for a in argv]
    done = subprocess.run([sys.executable, "-c", INTERRUPT_AT_IMPORT, module, at, "SIGINT", *argv],
                          capture_output=True, text=True, cwd=REPO, env=ENV, timeout=300)
    assert done.returncode == 130, done.stderr
    assert done.stderr.strip() == line, done.stderr
    assert not (tmp_path / "run").exists()


def test_a_sigterm_before_a_command_has_its_own_stop_is_one_line_and_143(tmp_path):
    # Its default would end the process without a word (and not at all as a container's process 1).
    done = subprocess.run([sys.executable, "-c", INTERRUPT_AT_IMPORT, "nasa.cli", "nasa.train", "SIGTERM",
                           "train", "--task", "cartpole-balance", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, cwd=REPO, env=ENV, timeout=300)
    assert done.returncode == 143, done.stderr
    assert done.stderr.strip() == "nasa train: stopped (SIGTERM)", done.stderr
    assert not (tmp_path / "run").exists()


def test_no_module_uses_another_modules_private_name():
    # nasa.reproduce took nasa.cli's private signal helpers; they are nasa.stopping's now.
    found = []
    for package in ("nasa", "services", "shared", "bench"):
        for path in sorted((REPO / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if (isinstance(node, ast.ImportFrom) and node.module
                        and node.module.split(".")[0] in ("nasa", "services", "shared", "bench")):
                    found += [f"{path.relative_to(REPO)}: {node.module}.{a.name}" for a in node.names
                              if a.name.startswith("_") and not a.name.startswith("__")]
    assert found == []


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_service_still_looking_for_its_router_stops_on_a_signal(tmp_path, signum):
    # Something listens on the router's port but speaks no Zenoh: the service's connection shows
    # it is trying, and it would go on trying for 30 s, then exit 3 (a router that refuses it).
    import socket

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        listener.settimeout(120)
        port = listener.getsockname()[1]
        replay = subprocess.Popen(
            [sys.executable, "-m", "services.replay", "--data", str(tmp_path / "run"),
             "--connect", f"tcp/127.0.0.1:{port}"], stderr=subprocess.PIPE, text=True, cwd=REPO, env=ENV)
        try:
            listener.accept()[0].close()
            replay.send_signal(signum)
            _, err = replay.communicate(timeout=120)
        finally:
            replay.kill()
    assert replay.returncode == 128 + signum, err
    assert err.strip() == (f"python -m services.replay: stopped ({signal.Signals(signum).name}) before it "
                           "connected"), err


# A service (shared.service.run_service, on a real router) whose stop takes long.
SLOW_SERVICE = """
import sys, time
from nasa.up import free_port
from shared.service import run_service
from shared.zenoh_session import ServiceArgs, open_router

def run(args, session, stop):
    print("running", flush=True)
    stop.wait()
    print("stopping", flush=True)
    time.sleep(600)

endpoint = f"tcp/127.0.0.1:{free_port()}"
with open_router(endpoint):
    run_service(ServiceArgs, ["--connect", endpoint], "python -m services.slow", run)
"""


@pytest.mark.parametrize("first", [signal.SIGINT, signal.SIGTERM])
def test_a_ctrl_c_after_a_first_signal_ends_a_slow_service_stop_at_once(first):
    service = start(SLOW_SERVICE, env={k: v for k, v in ENV.items() if k != "NASA_ZENOH_AUTH"})
    try:
        assert service.stdout.readline() == "running\n"
        service.send_signal(first)
        assert service.stdout.readline() == "stopping\n"
        service.send_signal(signal.SIGINT)
        _, err = service.communicate(timeout=120)
    finally:
        service.kill()
    assert service.returncode == 130, err
    assert err.strip() == "python -m services.slow: forced to stop (SIGINT)", err


# Rows in the log of the replay test below: far more than a stop signal takes to arrive.
LONG_LOG_ROWS = 200_000


@pytest.mark.timeout(600)
def test_a_replay_reopening_a_long_log_stops_on_a_signal_before_serving_and_loses_nothing(tmp_path):
    # A replay restarted on a long log reads all of it before it serves; a SIGTERM meanwhile (a
    # launcher stopping the run) ends it there, and the log stays whole for the next start.
    import hashlib

    import numpy as np

    from nasa.up import free_port
    from shared import run_config
    from shared.config import default_config
    from shared.replay.store import open_store
    from shared.zenoh_session import open_router

    config = default_config("nasa_td3", "cpu-small", "cartpole-balance")
    config.env.task, config.env.image_size = "cartpole-balance", 16
    config.replay_capacity, config.steps = LONG_LOG_ROWS, 2 * LONG_LOG_ROWS
    data = tmp_path / "run"
    run = run_config.open_folder(config, data)
    frame = np.zeros(run.spec.frame_shape, np.uint8)
    action = np.zeros(run.spec.action_dim, np.float32)
    with open_store(run, data / "replay") as store:
        for i in range(LONG_LOG_ROWS):
            if i % 1000 == 0:
                episode = store.begin_episode(frame)
            store.add(episode, action, 1.0, 1.0, frame, last=i % 1000 == 999)

    def log_digest() -> dict[str, str]:
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in (data / "replay").iterdir()}

    before = log_digest()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {k: v for k, v in ENV.items() if k != "NASA_ZENOH_AUTH"}
    with open_router(endpoint):
        replay = subprocess.Popen(
            [sys.executable, "-m", "services.replay", "--run-config", str(data / "config.json"), "--data",
             str(data), "--camera-checked", "--connect", endpoint],
            stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
        try:
            said = ""
            while ": reading its log" not in said and "serving run" not in said:
                line = replay.stderr.readline()
                assert line, said  # it ended before it read its log
                said += line
            replay.send_signal(signal.SIGTERM)
            _, err = replay.communicate(timeout=300)
        finally:
            replay.kill()
    assert replay.returncode == 143, said + err
    assert "serving run" not in said + err and "reopened" not in said + err, said + err
    assert "stopped (SIGTERM) before serving" in err and "Traceback" not in err, err
    assert log_digest() == before
    with open_store(run, data / "replay") as store:
        assert store.num_inserted == LONG_LOG_ROWS


@pytest.mark.parametrize(("signum", "said"), [(signal.SIGINT, "interrupted"),
                                              (signal.SIGTERM, "stopped (SIGTERM)")])
def test_a_stopped_runs_dashboard_ends_on_a_signal_with_one_line_and_its_code(tmp_path, signum, said):
    import httpx

    from nasa.up import free_port

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text('{"run_id": "r"}')
    port = free_port()
    serve = subprocess.Popen(
        [sys.executable, "-m", "nasa", "status", "--data", str(tmp_path), "--serve", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=ENV)
    try:
        assert "(Ctrl-C ends it)" in serve.stdout.readline()
        while True:  # serving: the server's own signal handlers are in place
            assert serve.poll() is None
            try:
                if httpx.get(f"http://127.0.0.1:{port}/status", timeout=10).json() == {"run_id": "r"}:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        serve.send_signal(signum)
        _, err = serve.communicate(timeout=120)
    finally:
        serve.kill()
    assert serve.returncode == 128 + signum, err
    assert err.strip() == f"nasa status: {said}", err
