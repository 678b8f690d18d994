"""How a benchmark stops on Ctrl-C or SIGTERM, and stops the processes it started.

Python's default SIGTERM ends a process without running its `finally` blocks: the temporary
folders stay, and a child started in a session of its own (`nasa up`, `nasa train`, which no
signal to the benchmark reaches) goes on holding its ports and cores. Standard library and
nasa.stopping only, as bench.gpu imports it before its set-up step.

A child whose output comes through a pipe must have it read all along (Drain): a pipe holds
some 64 KiB, and a child that finds it full stops at its next line until someone reads.

A benchmark killed by SIGKILL runs no `finally` block: a `nasa up` or `nasa train` it started with
`shared.service.followed()` stops its run then too.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from nasa.stopping import Terminated, interrupted, raise_terminated

# nasa up and nasa train stop their children in order on SIGINT; SIGTERM next, for a child that
# ignores SIGINT (one started in the background by a non-interactive shell).
STOP_STEPS: tuple[tuple[int, float], ...] = ((signal.SIGINT, 20.0), (signal.SIGTERM, 60.0))


@contextlib.contextmanager
def stopped_cleanly(prog: str) -> Iterator[None]:
    """Around a benchmark's main: SIGTERM is raised as Terminated where the main thread is, as
    Ctrl-C raises KeyboardInterrupt, so every `finally` block runs (children stopped, temporary
    folders removed); then one line, not a traceback, and exit 130 or 143."""
    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        with interrupted(prog):
            yield
    finally:
        signal.signal(signal.SIGTERM, previous)


GROUP_POLL_S = 0.1
"""How often a group whose leader has exited is looked at, while the rest of it stops."""


def _kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _group_gone(proc: subprocess.Popen) -> bool:
    """Whether the leader has exited and no live process is left in its group (the group's id stays
    taken while one is, so it cannot name another group meanwhile). A member that exited but was
    not reaped stays in the group as a zombie, and one whose parent never reaps it (an orphan where
    a container's first process reaps nothing) would stay for ever: zombies do not count."""
    if proc.poll() is None:
        return False
    try:
        os.killpg(proc.pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # a member this process may not signal: the scan below sees it
        pass
    return not _live_members(proc.pid)


def _wait_group(proc: subprocess.Popen, grace: float) -> None:
    """Wait up to `grace` seconds for the leader to exit, then for the rest of its group."""
    deadline = time.monotonic() + grace
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=grace)
    while not _group_gone(proc) and time.monotonic() < deadline:
        time.sleep(GROUP_POLL_S)


def stop_group(proc: subprocess.Popen, steps: tuple[tuple[int, float], ...] = STOP_STEPS) -> int:
    """Stop `proc`, started with start_new_session=True, and its process group: each signal of
    `steps` in turn to the whole group, waiting its grace for the leader to exit and the rest of
    the group with it, then SIGKILL to whatever is left, members the leader left behind too. A
    Ctrl-C or SIGTERM while it waits (the user insisting) kills the group at once and is raised
    again. Returns the leader's exit code."""
    try:
        for sig, grace in steps:
            if _group_gone(proc):
                break
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            _wait_group(proc, grace)
    except (KeyboardInterrupt, Terminated):
        _kill_group(proc)
        raise
    if not _group_gone(proc):
        _kill_group(proc)
    return proc.returncode


def _stat(proc: Path) -> list[bytes]:
    """A /proc/<pid>/stat's fields after the process's name (state, ppid, pgrp, ...); bytes: a
    process's name need not be UTF-8, and it may hold spaces and parentheses."""
    return (proc / "stat").read_bytes().rsplit(b")", 1)[1].split()


def _processes() -> Iterator[Path]:
    return (proc for proc in Path("/proc").iterdir() if proc.name.isdigit())


def _live_members(pgid: int) -> list[int]:
    """The processes of group `pgid` that are not zombies."""
    members = []
    for proc in _processes():
        try:
            fields = _stat(proc)
            state, pgrp = fields[0], int(fields[2])
        except (OSError, IndexError, ValueError):  # gone meanwhile
            continue
        if pgrp == pgid and state != b"Z":
            members.append(int(proc.name))
    return members


def processes_with(variable: str, value: str) -> list[tuple[int, list[str]]]:
    """The live processes (pid, argv) whose environment holds `variable`=`value`, which every
    process they start inherits, whatever its session; zombies and processes gone meanwhile are
    left out."""
    entry = f"{variable}={value}".encode()
    found = []
    for proc in _processes():
        try:
            if entry not in (proc / "environ").read_bytes().split(b"\0"):
                continue
            # Bytes: a process's argv or environment need not be UTF-8.
            if _stat(proc)[0] == b"Z":
                continue
            argv = (proc / "cmdline").read_bytes().decode(errors="replace").split("\0")
            found.append((int(proc.name), argv))
        except OSError:
            continue
    return found


class Drain:
    """Reads a child's output `stream` to its end in a thread of its own, so the child never blocks
    on a full pipe, and keeps its last `keep` lines (after `first`, the lines read before) for an
    error message. Open the stream with errors="replace": a line that cannot be decoded must not
    end the reading."""

    def __init__(self, stream: IO[str], first: Iterable[str] = (), keep: int = 200) -> None:
        self._lines: deque[str] = deque(first, maxlen=keep)
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(stream,), name="drain", daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        with contextlib.suppress(OSError, ValueError):  # the stream closed under it
            for line in stream:
                with self._lock:
                    self._lines.append(line)

    def lines(self, wait_s: float = 10.0) -> list[str]:
        """The last lines kept, once the output has ended (or after `wait_s`: a process of the
        child's may still hold the pipe open)."""
        self._thread.join(wait_s)
        with self._lock:
            return list(self._lines)
