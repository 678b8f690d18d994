"""Who holds a running Python process's interpreter lock: py-spy's samples, by thread and function.

A learner whose update is bound by the host spends its time in Python, under one lock that every
thread of the process shares (the update loop, the batch prefetcher, the device stager, Zenoh's
callbacks, the status server). `py-spy record --gil` samples only the thread holding the lock, so
each thread's share of the samples is its share of the lock: a thread that takes much of it slows
the update loop down by as much.

py-spy (a dev requirement; on a machine without network access, its wheel unzipped anywhere and
`PY_SPY` set to the `py-spy` binary inside) needs to be allowed to read the process's memory:
root, or ptrace allowed for the user.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

RATE_HZ = 100
_FRAME = re.compile(r"^(?P<name>.*) \((?P<file>.*):\d+\)$")


class GilProfileError(RuntimeError):
    pass


def find_py_spy() -> str | None:
    """$PY_SPY, py-spy on PATH, or beside this Python (a venv's bin)."""
    beside = str(Path(sys.executable).parent / "py-spy")
    for candidate in (os.environ.get("PY_SPY"), shutil.which("py-spy"), beside):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


class Recording:
    """py-spy sampling `pid` for `seconds`, started now; `result()` waits for it and summarizes."""

    def __init__(self, pid: int, seconds: float, out: Path, rate_hz: int = RATE_HZ) -> None:
        spy = find_py_spy()
        if spy is None:
            raise GilProfileError("py-spy not found (pip install py-spy, or set PY_SPY to its binary)")
        # py-spy records whole seconds: the shares are of the duration it records, not the one asked.
        self.seconds, self.rate_hz, self.out = max(1, round(seconds)), rate_hz, Path(out)
        cmd = [spy, "record", "--pid", str(pid), "--duration", str(self.seconds),
               "--rate", str(rate_hz), "--format", "raw", "--output", str(self.out),
               "--threads", "--gil", "--nonblocking"]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def result(self, timeout_s: float = 60.0) -> dict:
        try:
            output, _ = self.proc.communicate(timeout=self.seconds + timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise GilProfileError("py-spy did not finish") from None
        if self.proc.returncode != 0 or not self.out.exists():
            raise GilProfileError(f"py-spy failed (exit {self.proc.returncode}): {output.strip()[-400:]}")
        return summarize(self.out.read_text(), self.seconds, self.rate_hz)


def summarize(raw: str, seconds: float, rate_hz: int = RATE_HZ, top: int = 12) -> dict:
    """py-spy's raw output (`thread (tid): name;frame;...;frame count` per line) as shares of the
    wall clock: each thread's hold of the lock, and the main thread's functions (inclusive: a
    function counts once per sample that has it anywhere on its stack)."""
    expected = seconds * rate_hz
    threads: Counter[str] = Counter()
    functions: Counter[str] = Counter()
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        thread, *frames = stack.split(";")
        name = thread.split(": ", 1)[1] if ": " in thread else thread
        threads[name] += n
        if name == "MainThread":
            for function in {short_frame(f) for f in frames}:
                functions[function] += n
    return {
        "seconds": seconds,
        "samples": sum(threads.values()),
        "gil_share_by_thread": {k: round(v / expected, 3) for k, v in threads.most_common()},
        "main_thread_functions": {k: round(v / expected, 3) for k, v in functions.most_common(top)},
    }


def short_frame(frame: str) -> str:
    """`update (/x/y/shared/agents/td3.py:97)` -> `update (agents/td3.py)`: a function, not a line."""
    match = _FRAME.match(frame)
    if match is None:
        return frame
    parts = Path(match["file"]).parts
    return f"{match['name']} ({'/'.join(parts[-2:])})"
