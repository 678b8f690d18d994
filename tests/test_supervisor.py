"""nasa up's Supervisor with real, tiny child processes (no Zenoh): restart, exit 0, exit 2, stop order."""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path

import pytest

from nasa.up import STOP_ORDER, Supervisor, run_ends

# Each child runs `python -c SCRIPT <role> <folder>`.
EXIT_WITH = "import sys; print('child says: bad flag --x', flush=True); sys.exit(int(sys.argv[2]))"
# As EXIT_WITH, but with code 0 it runs on.
EXIT_OR_RUN_ON = EXIT_WITH.replace("import sys", "import sys, time").replace(
    "sys.exit(int(sys.argv[2]))", "int(sys.argv[2]) and sys.exit(int(sys.argv[2])); time.sleep(60)")
WAIT_FOR_SIGTERM = """
import pathlib, signal, sys, time
role, folder = sys.argv[1], pathlib.Path(sys.argv[2])
def on_term(signum, frame):
    with open(folder / "stopped", "a") as f:
        f.write(role + "\\n")
    sys.exit(0)
signal.signal(signal.SIGTERM, on_term)
(folder / f"ready-{role}").touch()
while True:
    time.sleep(0.05)
"""
IGNORE_SIGTERM = """
import pathlib, signal, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
(pathlib.Path(sys.argv[2]) / f"ready-{sys.argv[1]}").touch()
while True:
    time.sleep(0.05)
"""


def supervisor(tmp_path: Path, script: str, **kwargs) -> Supervisor:
    return Supervisor({}, tmp_path / "logs", restart_delay_s=0.0,
                      command=lambda role: [sys.executable, "-c", script, role], **kwargs)


def poll_until(sup: Supervisor, done, events: list[str], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"supervisor did not get there; events: {events}"
        sup.poll(events.append)
        time.sleep(0.02)


def wait_ready(folder: Path, roles: list[str], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not all((folder / f"ready-{r}").exists() for r in roles):
        assert time.monotonic() < deadline, "children did not start"
        time.sleep(0.02)


def test_a_child_that_dies_is_restarted_up_to_max_restarts(tmp_path):
    sup = supervisor(tmp_path, EXIT_WITH, max_restarts=2)
    child = sup.add("actor-0", "actor", ["1"])
    events: list[str] = []
    poll_until(sup, lambda: child.exited is not None, events)
    assert child.restarts == 2 and child.exited == 1
    assert len(child.pids) == 3 and len(set(child.pids)) == 3
    # Each line says why, from the child's log (with --logs its error is nowhere else in sight).
    why = f"({tmp_path / 'logs' / 'actor-0.log'}: child says: bad flag --x)"
    assert [e for e in events if "restarting" in e] == [
        f"actor-0 exited with 1 {why}: restarting it (1)", f"actor-0 exited with 1 {why}: restarting it (2)"]
    assert events[-1] == f"actor-0 exited with 1 {why}; not restarted after 2 restarts in a row"
    assert sup.ended(("actor",)) is child and sup.ended(("learner",)) is None


def test_restarts_in_a_row_back_off_and_a_child_that_ran_well_starts_its_count_again(tmp_path):
    sup = Supervisor({}, tmp_path / "logs", restart_delay_s=0.1, max_restarts=3,
                     command=lambda role: [sys.executable, "-c", EXIT_WITH, role])
    child = sup.add("actor-0", "actor", ["1"])
    events: list[str] = []
    start = time.monotonic()
    poll_until(sup, lambda: child.exited is not None, events)
    assert child.restarts == 3 and time.monotonic() - start >= 0.1 + 0.2 + 0.4  # waits doubling
    steady = Supervisor({}, tmp_path / "logs2", restart_delay_s=0.0, max_restarts=1, stable_s=0.0,
                        command=lambda role: [sys.executable, "-c", EXIT_WITH, role])
    again = steady.add("actor-1", "actor", ["1"])
    poll_until(steady, lambda: len(again.pids) >= 4, events)  # each run counted as a fresh start
    assert again.exited is None
    steady.stop_all()


def test_the_run_has_no_actor_left_once_every_actor_ended_for_good(tmp_path):
    sup = supervisor(tmp_path, EXIT_WITH)
    refused = [sup.add(f"actor-{i}", "actor", ["2"]) for i in range(2)]
    events: list[str] = []
    poll_until(sup, lambda: all(c.exited is not None for c in refused), events)
    assert sup.all_ended("actor") is refused[-1]
    done = supervisor(tmp_path / "done", EXIT_WITH)
    finished = [done.add("actor-0", "actor", ["2"]), done.add("actor-1", "actor", ["0"])]  # its steps done
    poll_until(done, lambda: all(c.exited is not None for c in finished), events)
    assert done.all_ended("actor") is None


def test_a_child_killed_by_a_signal_is_said_so_with_its_logs_last_line(tmp_path):
    sup = supervisor(tmp_path, WAIT_FOR_SIGTERM, max_restarts=0)
    child = sup.add("actor-0", "actor", [str(tmp_path)])
    wait_ready(tmp_path, ["actor"])
    (tmp_path / "logs" / "actor-0.log").write_text("x" * 100_000 + "\nacting on step 7\n")
    child.proc.kill()
    events: list[str] = []
    poll_until(sup, lambda: child.exited is not None, events)
    log = tmp_path / "logs" / "actor-0.log"
    assert events == [f"actor-0 was killed by SIGKILL ({log}: acting on step 7); "
                      "not restarted after 0 restarts in a row"]


def test_a_child_is_restarted_when_its_log_folder_is_gone_or_cannot_be_written(tmp_path):
    """Its logs removed to free space, then a service dies: the restart makes its log again. A log
    that cannot be written sends the output to the terminal; neither stops the run."""
    import shutil

    sup = supervisor(tmp_path, EXIT_WITH, max_restarts=1)
    child = sup.add("actor-0", "actor", ["1"])
    child.proc.wait()
    shutil.rmtree(tmp_path / "logs")
    events: list[str] = []
    poll_until(sup, lambda: child.restarts == 1, events)
    child.proc.wait()
    assert (tmp_path / "logs" / "actor-0.log").read_text() == "child says: bad flag --x\n"
    shutil.rmtree(tmp_path / "logs")
    (tmp_path / "logs").write_text("")  # a file where the folder was: no log can be made
    other = sup.add("actor-1", "actor", ["1"])
    poll_until(sup, lambda: other.restarts == 1, events)
    assert f"actor-1's log {tmp_path / 'logs' / 'actor-1.log'} cannot be written" in events[-1], events
    assert len(other.pids) == 2


def test_a_child_that_died_on_a_full_disk_is_said_so(tmp_path):
    """Its error could not be written to its log (the disk is full): nasa up says what it can."""
    from tests.test_hardening_faults import tmpfs

    with tmpfs(tmp_path / "full", "size=64k") as full:
        sup = Supervisor({}, full / "logs", restart_delay_s=0.0, max_restarts=0,
                         command=lambda role: [sys.executable, "-c", "import sys; sys.exit(1)", role])
        with contextlib.suppress(OSError):
            (full / "fill").write_bytes(b"x" * 128 * 1024)
        child = sup.add("learner", "learner", [])  # as a service that cannot write its error
        events: list[str] = []
        poll_until(sup, lambda: child.exited is not None, events)
        assert events == [f"learner exited with 1 ({full / 'logs' / 'learner.log'}: no output; no space is "
                          "left on its disk); not restarted after 0 restarts in a row"]


def test_a_restart_that_cannot_start_a_process_is_tried_again(tmp_path):
    """No process to be had at a restart (a pids limit, memory): said, and tried again, not raised
    out of nasa up, which would end the run."""
    fork_fails = {"now": False}

    def command(role: str) -> list[str]:
        if fork_fails["now"]:
            raise BlockingIOError(11, "Resource temporarily unavailable")
        return [sys.executable, "-c", EXIT_WITH, role]

    sup = Supervisor({}, tmp_path / "logs", restart_delay_s=0.0, max_restarts=3, command=command)
    child = sup.add("actor-0", "actor", ["1"])
    fork_fails["now"] = True
    events: list[str] = []
    poll_until(sup, lambda: child.restarts == 1, events)
    assert events[-1] == "actor-0 could not be started (Resource temporarily unavailable); trying again"
    fork_fails["now"] = False
    poll_until(sup, lambda: len(child.pids) == 2, events)
    assert child.restarts == 2 and child.exited is None
    # A child that ran well for long, then no process for it at all: the failed starts count in a
    # row, so it ends for good rather than being tried forever.
    child.proc.wait()
    child.started -= 10 * sup.stable_s
    fork_fails["now"] = True
    poll_until(sup, lambda: child.exited is not None, events)
    assert child.restarts == 3 and len(child.pids) == 2
    assert events[-1].startswith("actor-0 exited with 1") and events[-1].endswith("after 3 restarts in a row")


def test_a_child_that_exits_0_is_not_restarted(tmp_path):
    sup = supervisor(tmp_path, EXIT_WITH)
    child = sup.add("learner", "learner", ["0"])
    events: list[str] = []
    poll_until(sup, lambda: child.exited is not None, events)
    assert child.exited == 0 and child.restarts == 0 and len(child.pids) == 1
    assert events == []


def test_a_child_that_refuses_its_input_is_not_restarted_and_its_error_is_reported(tmp_path):
    sup = supervisor(tmp_path, EXIT_WITH)
    child = sup.add("replay", "replay", ["2"])
    events: list[str] = []
    poll_until(sup, lambda: child.exited is not None, events)
    assert child.exited == 2 and child.restarts == 0 and len(child.pids) == 1
    assert events == [f"replay refused its input: {tmp_path / 'logs' / 'replay.log'}: "
                      "child says: bad flag --x; not restarted"]
    assert sup.ended(("learner", "replay")) is child


def test_a_child_whose_login_is_refused_is_not_restarted_and_ends_the_run(tmp_path):
    # The run's router and credentials do not change while it runs: a restart would be refused again.
    sup = supervisor(tmp_path, EXIT_OR_RUN_ON)
    learner = sup.add("learner", "learner", ["0"])  # runs on
    actor = sup.add("actor-1", "actor", ["3"])
    events: list[str] = []
    poll_until(sup, lambda: actor.exited is not None, events)
    assert actor.exited == 3 and actor.restarts == 0 and len(actor.pids) == 1
    assert f"actor-1's Zenoh login was refused by the router: {tmp_path / 'logs' / 'actor-1.log'}: " \
           "child says: bad flag --x; not restarted" in events
    ended, why = run_ends(sup, tmp_path / "auth")
    assert ended is actor and learner.exited is None
    assert why == ("actor-1's Zenoh login was refused by the run's router: its credentials "
                   f"({tmp_path / 'auth'}) are not the router's, and a restart would not change them")
    sup.stop_all(timeout_s=10.0)


def test_stop_all_stops_role_by_role_in_order(tmp_path):
    sup = supervisor(tmp_path, WAIT_FOR_SIGTERM)
    roles = ["replay", "learner", "robot_bridge", "actor", "evaluator"]  # not in the order they stop
    for role in roles:
        sup.add(role, role, [str(tmp_path)])
    wait_ready(tmp_path, roles)
    sup.stop_all(timeout_s=10.0)
    assert (tmp_path / "stopped").read_text().split() == list(STOP_ORDER)
    assert sup.running() == []
    assert all(c.proc.returncode == 0 for c in sup.children.values())


def test_stop_all_kills_a_child_that_ignores_sigterm(tmp_path):
    sup = supervisor(tmp_path, IGNORE_SIGTERM)
    child = sup.add("actor-0", "actor", [str(tmp_path)])
    wait_ready(tmp_path, ["actor"])
    said: list[str] = []
    sup.stop_all(timeout_s=0.5, on_event=said.append)
    assert child.proc.returncode == -9  # SIGKILL after the timeout, and said
    assert said == ["actor-0 did not stop within 0.5 s of SIGTERM: killed"]
    events: list[str] = []
    sup.poll(events.append)  # stopping: nothing is restarted
    assert child.exited == -9 and events == [] and len(child.pids) == 1


@pytest.mark.parametrize("code", [1, 2])
def test_nothing_is_restarted_while_stopping(tmp_path, code):
    sup = supervisor(tmp_path, EXIT_WITH)
    child = sup.add("actor-0", "actor", [str(code)])
    child.proc.wait()
    sup.stopping = True
    sup.poll(lambda msg: None)
    assert child.exited == code and child.restarts == 0


def test_a_child_gets_its_own_environment_over_the_supervisors(tmp_path):
    script = ("import os, pathlib, sys; pathlib.Path(sys.argv[2], sys.argv[1]).write_text("
              "repr((os.environ.get('OMP_WAIT_POLICY'), os.environ.get('KEEP'))))")
    sup = Supervisor({"OMP_WAIT_POLICY": "PASSIVE", "KEEP": "1"}, tmp_path / "logs", restart_delay_s=0.0,
                     command=lambda role: [sys.executable, "-c", script, role])
    children = [sup.add("learner", "learner", [str(tmp_path)], env={"OMP_WAIT_POLICY": "ACTIVE"}),
                sup.add("evaluator", "evaluator", [str(tmp_path)], env={"OMP_WAIT_POLICY": None}),
                sup.add("actor-0", "actor", [str(tmp_path)])]
    poll_until(sup, lambda: all(c.exited is not None for c in children), [])
    seen = {role: (tmp_path / role).read_text() for role in ("learner", "evaluator", "actor")}
    assert seen == {"learner": "('ACTIVE', '1')", "evaluator": "(None, '1')", "actor": "('PASSIVE', '1')"}
