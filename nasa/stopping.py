"""How the `nasa` commands stop on a signal: Ctrl-C (SIGINT), SIGTERM, SIGHUP.

The first stop signal stops a command in order (its children, then its files) and exits 128 + the
signal (130, 143, 129), the shell's convention; a second one during that stop forces it: what is
left is killed and the command exits at once. Forcing is as safe as a SIGKILL, which every file
of a run survives (checkpoints and whole-file writes land by an atomic rename; the replay's log
and the CSV logs drop a record cut short).

Standard library only: the entry point imports it before anything heavy, so a Ctrl-C during
start-up is one line too.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Callable, Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Terminated(Exception):
    """SIGTERM, raised where the run is, as Ctrl-C raises KeyboardInterrupt: the same clean stop."""


_raised: list[int] = []
"""The stop signals raised as exceptions in this process. Python code that a C extension calls
back (ctypes converting an argument: PyOpenGL's EGL calls while a frame renders) can be where the
signal's exception is raised, and the extension replaces it with its own (ctypes' ArgumentError
"argument 4: Terminated: "): `stop_code` still knows it was the stop."""


def raise_terminated(_signum: int, _frame: object) -> None:
    """A SIGTERM handler: raise Terminated where the main thread is."""
    _raised.append(signal.SIGTERM)
    raise Terminated


def raise_interrupt(_signum: int, _frame: object) -> None:
    """A SIGINT handler: raise KeyboardInterrupt, as Python's own does, and remember it."""
    _raised.append(signal.SIGINT)
    raise KeyboardInterrupt


def raise_on_stop_signals() -> None:
    """Ctrl-C and SIGTERM raise where the main thread is (KeyboardInterrupt, Terminated)."""
    signal.signal(signal.SIGTERM, raise_terminated)
    signal.signal(signal.SIGINT, raise_interrupt)


def signal_code(err: BaseException) -> int:
    """128 + the signal that raised `err` (130, 143), the shell's convention."""
    return 128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT)


def stop_code(err: BaseException) -> int | None:
    """128 + the stop signal behind `err`, raised as itself or replaced by a C extension on its way
    out (see `_raised`): once a stop signal was raised here, the error that ends the run is taken
    as its stop; None where none was."""
    if isinstance(err, (KeyboardInterrupt, Terminated)):
        return signal_code(err)
    return 128 + _raised[-1] if _raised else None


def ignore_stop_signals() -> None:
    """A second Ctrl-C or SIGTERM would cut the stop message short; the run is stopping anyway."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def shares_launchers_ctrl_c() -> bool:
    """Whether this process's launcher (NASA_PARENT_PID) is in its process group, as `nasa reproduce`
    is with its `nasa train`s: a terminal's Ctrl-C then reaches both, and the SIGTERM the launcher
    sends after it is no second signal. A launcher that started it in a session of its own (the
    benchmarks) shares no Ctrl-C with it."""
    try:
        return os.getpgid(int(os.environ.get("NASA_PARENT_PID", ""))) == os.getpgrp()
    except (ValueError, OSError):  # no launcher, or it is gone
        return False


def write_line(line: str, fd: int = 2) -> None:
    """`line` on `fd`, unbuffered: safe inside a signal handler, where print() may find its stream's
    buffer in the middle of another write; nothing where the stream is gone (a closed terminal)."""
    with contextlib.suppress(OSError):
        os.write(fd, (line + "\n").encode(errors="replace"))


def second_signal_forces(prog: str, after: str, force: Callable[[], str] | None = None,
                         signals: tuple[int, ...] = STOP_SIGNALS, fd: int = 2) -> None:
    """From now on, the next of `signals` ends this process at once with 128 + it: `force()` first
    (it kills what is left and says what it did), then one line: `prog` was forced to stop, what
    force did, and `after` (how the run goes on).

    os._exit: no finally block or atexit handler runs, as none may wait on what is being forced."""

    def handler(signum: int, _frame: object) -> None:
        try:
            done = force() if force is not None else ""
        except Exception as err:  # noqa: BLE001 -- the exit below must come whatever happened
            done = f"not all was killed: {err}"
        said = "; ".join(part for part in (done, after) if part)
        write_line(f"{prog}: forced to stop ({signal.Signals(signum).name}); {said}", fd)
        os._exit(128 + signum)

    for signum in signals:
        signal.signal(signum, handler)


@contextlib.contextmanager
def interrupted(prog: str, when: str = "") -> Iterator[None]:
    """Around what has no stop of its own (start-up's imports, a command before its handlers): a
    Ctrl-C there, or a SIGTERM raised as Terminated, is one line and 128 + the signal, not a
    traceback."""
    try:
        yield
    except (KeyboardInterrupt, Terminated) as err:
        how = "interrupted" if isinstance(err, KeyboardInterrupt) else "stopped (SIGTERM)"
        write_line(f"\n{prog}: {how}{' ' + when if when else ''}")
        sys.exit(signal_code(err))
