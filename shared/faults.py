"""What a process does when it cannot go on: a run folder another run holds, a read-only folder, a busy
port, a worker thread that died.

A run folder belongs to one run at a time (PostgreSQL's pid file, with `fcntl.flock`):

- `<data>/.lock` is the run's lock. A launcher (`nasa up`, `nasa train`) holds it exclusively and
  writes its pid, host and command into it. The services a launcher starts find their launcher's pid
  there (NASA_PARENT_PID) and take no part of it; a service started without a launcher (the compose
  file) holds it shared, so the services of one deployment may share a folder while a launcher may not
  join them.
- `<data>/.lock.<role>` is held exclusively by each service that writes there (replay, learner,
  evaluator), so two replays never write one log, whoever started them.

The kernel drops a lock when its process dies (kill -9 included): a stale lock file never blocks a
restart. A held lock, a read-only folder or a busy port is a `RunFolderError` (a ConfigError: one
line, exit 2, never restarted).

A launcher killed with SIGKILL leaves its services stopping (each got SIGTERM) and holding their
role's lock for a while (a learner's last checkpoint, an evaluation under way). So a launcher that
takes the run's lock first waits, up to SERVICES_EXIT_S, for every role's lock to be free: the same
command again then starts every service, where the one still stopping would refuse its restart.

A file lock covers one host. Across hosts the replay, the learner, the evaluator and a robot bridge
are each one process per run (per id for a bridge): before serving, each looks for its role's
liveliness token (`claim_role`) and, if another process holds it, refuses with `RoleTaken` (a
RunFolderError). Two replays would each take every insert and answer every sample; two learners
would publish two policies; two bridges would both move for every step.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from shared.config import ConfigError

if TYPE_CHECKING:
    import zenoh

    from shared import wire
    from shared.service import Log, StopFlag

LOCK = ".lock"


class RunFolderError(ConfigError):
    """The run folder or a port cannot be had: another run holds it, or it cannot be written."""


class RunHeld(RunFolderError):
    """Another launcher holds the run folder's lock."""


class RoleTaken(RunFolderError):
    """Another process already serves this role of the run (its liveliness token is up)."""


SERVICES_EXIT_S = 60.0
"""How long a launcher waits for the services of an earlier launch on its folder to exit."""

TOKEN_LEASE_S = 12.0
"""Longer than Zenoh's default lease (10 s): by then the token of a process that died without
closing its link (a crashed host) is gone."""


def claim_role(session: zenoh.Session, key: str, stop: StopFlag, log: Log, what: str, hint: str) -> bool:
    """True once no other process holds the liveliness token `key` of `what`: at once, or within
    TOKEN_LEASE_S (a process that died just before this one's restart). False if `stop` came first.
    RoleTaken, with `hint`, if it is still held then."""
    from shared.zenoh_session import token_up  # zenoh only for services

    if not token_up(session, key):
        return True
    log(f"{what} has a live token already: waiting {TOKEN_LEASE_S:.0f} s in case its process just died")
    deadline = time.monotonic() + TOKEN_LEASE_S
    while time.monotonic() < deadline:
        if stop.wait(1.0):
            return False
        if not token_up(session, key):
            return True
    raise RoleTaken(f"{what} is served by another process already ({key} is up): {hint}")


def claim_run_role(session: zenoh.Session, keys: wire.Keys, role: str, stop: StopFlag, log: Log) -> bool:
    """`claim_role` for a run's one replay, learner or evaluator."""
    hint = f"one {role} serves a run; stop that one first"
    return claim_role(session, keys.alive(role, 0), stop, log, f"run {keys.run_id}'s {role}", hint)


class WorkerDied(RuntimeError):
    """A worker thread of a service ended while the service runs: the process exits non-zero so its
    supervisor restarts it, rather than living on doing nothing."""


class RunLock:
    """The locks one process holds on a run folder; released when it closes or dies."""

    def __init__(self) -> None:
        self._fds: list[int] = []

    def close(self) -> None:
        for fd in self._fds:
            os.close(fd)
        self._fds = []

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _take(self, path: Path, exclusive: bool, what: str) -> bool:
        """flock `path`; False if another process holds it (in a way that excludes this one)."""
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise RunFolderError(f"{path.parent} cannot be written ({err.strerror}): {what}") from err
        try:
            fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return False
        self._fds.append(fd)
        if exclusive:
            try:
                _write_owner(fd, what)
            except OSError as err:  # a full disk: the lock would name no one; the run could write nothing
                self.close()
                raise RunFolderError(f"{path.parent} cannot be written ({err.strerror}): {what}") from err
        return True


def _write_owner(fd: int, what: str) -> None:
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}: {what}\n".encode(), 0)


def owner(data: Path, role: str | None = None) -> str:
    """Who holds the run's lock (or a service's), as its lock file says. The file names the last
    process that held it alone; services hold the run's lock together and name no one, so a named
    process of this host that has exited is said to be gone."""
    path = Path(data) / (LOCK if role is None else f"{LOCK}.{role}")
    try:
        text = path.read_text().strip()
    except OSError:
        return "another process"
    if not text:
        return "another process"
    match = re.match(r"pid (\d+) on (\S+): ", text)
    if match and match.group(2) == socket.gethostname() and not _alive(int(match.group(1))):
        return f"its services; the launcher the lock file names ({text}) has exited"
    return text


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def lock_run(data: Path, what: str, flag: str = "--data", wait_s: float = SERVICES_EXIT_S,
             say: Callable[[str], None] | None = None) -> RunLock:
    """A launcher's exclusive lock on the run folder `data` (created if missing); `flag` is the
    launcher's option that names the folder, for the error. Then waits up to `wait_s` for the
    services of an earlier launch that still hold their role's lock, saying so with `say`."""
    data = Path(data)
    _writable(data, what)
    lock = RunLock()
    if not lock._take(data / LOCK, True, what):
        raise RunHeld(f"{data} belongs to another run ({owner(data)}); stop it or use another {flag}")
    try:
        _wait_for_services(data, wait_s, say or (lambda msg: print(msg, file=sys.stderr, flush=True)))
    except BaseException:
        lock.close()
        raise
    return lock


def _wait_for_services(data: Path, wait_s: float, say: Callable[[str], None]) -> None:
    """Wait until no role's lock in `data` is held. With the run's lock held alone, whoever holds one
    is a service whose launcher died: it got SIGTERM (PR_SET_PDEATHSIG) and is on its way out."""
    deadline = time.monotonic() + wait_s
    for path in sorted(data.glob(f"{LOCK}.*")):
        role = path.name[len(LOCK) + 1 :]
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:  # gone, or unreadable: its service will say so when it starts
            continue
        try:
            said = False
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break  # free: released when fd closes
                except BlockingIOError:
                    pass
                if time.monotonic() >= deadline:
                    raise RunFolderError(
                        f"{data}: the {role} of an earlier launch on this folder ({owner(data, role)}) "
                        f"has not exited within {wait_s:g} s; stop that process, then start again")
                if not said:
                    say(f"the {role} of an earlier launch on {data} is still stopping "
                        f"({owner(data, role)}): waiting up to {wait_s:g} s for it to exit")
                    said = True
                time.sleep(0.2)
        finally:
            os.close(fd)


def lock_service(data: Path, role: str) -> RunLock:
    """A writing service's locks: the run's (shared, unless its launcher holds it) and its role's."""
    data = Path(data)
    what = f"the {role} of a run"
    _writable(data, what)
    lock = RunLock()
    parent = os.environ.get("NASA_PARENT_PID")
    mine = parent is not None and owner(data).startswith(f"pid {parent} ")
    if not mine and not lock._take(data / LOCK, False, what):
        lock.close()
        raise RunHeld(f"{data} belongs to another run ({owner(data)})")
    if not lock._take(data / f"{LOCK}.{role}", True, what):
        lock.close()
        raise RunFolderError(f"{data} has a {role} already ({owner(data, role)})")
    return lock


def _writable(data: Path, what: str) -> None:
    try:
        data.mkdir(parents=True, exist_ok=True)
        probe = data / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise RunFolderError(f"{data} cannot be written ({err.strerror or err}): {what}") from err


def check_port_free(host: str, port: int, what: str, flag: str) -> None:
    """RunFolderError if `port` on `host` cannot be listened on (another process has it, or it is
    not a TCP port); the message names `flag`, the option that chooses another."""
    if not 1 <= port <= 65535:
        raise RunFolderError(f"{what} port must be a TCP port, 1-65535, got {port}")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn and Zenoh bind
        try:
            s.bind((host, port))
        except OSError as err:
            busy = err.errno == errno.EADDRINUSE
            why = "is in use by another process" if busy else f"cannot be used ({err.strerror})"
            raise RunFolderError(f"{what} port {port} on {host} {why}; choose another with {flag}") from err
