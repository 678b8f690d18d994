"""bench.gil_profile: py-spy's raw samples read as shares of the interpreter lock, and a real
recording of a real process with two busy threads."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

from bench.gil_profile import GilProfileError, Recording, find_py_spy, short_frame, summarize

MAIN = "thread (101): MainThread;<module> (/r/services/learner/__main__.py:6)"
RAW = "\n".join([
    f"{MAIN};train_on (/r/services/learner/core.py:80);update (/r/shared/agents/base.py:190) 50",
    f"{MAIN};train_on (/r/services/learner/core.py:75);score_new (/r/shared/scoring.py:60) 20",
    f"{MAIN};f (/r/x.py:1);f (/r/x.py:2) 5",
    "thread (202): prefetch;_run (/r/shared/replay/client.py:300) 15",
    "garbage line",
])


def test_summarize_gives_each_threads_share_and_the_main_threads_functions():
    out = summarize(RAW, seconds=1.0, rate_hz=100)
    assert out["samples"] == 90
    assert out["gil_share_by_thread"] == {"MainThread": 0.75, "prefetch": 0.15}
    functions = out["main_thread_functions"]
    assert functions["<module> (learner/__main__.py)"] == 0.75
    assert functions["train_on (learner/core.py)"] == 0.7  # two lines of one function, one entry
    assert functions["update (agents/base.py)"] == 0.5
    assert functions["f (r/x.py)"] == 0.05  # a recursive function counts once per sample
    assert list(functions)[0] == "<module> (learner/__main__.py)"  # most first


def test_short_frame_names_a_function_and_its_file_not_a_line():
    assert short_frame("update_step (/a/b/shared/agents/td3.py:97)") == "update_step (agents/td3.py)"
    assert short_frame("<native>") == "<native>"


def test_recording_without_py_spy_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setattr("bench.gil_profile.find_py_spy", lambda: None)
    with pytest.raises(GilProfileError, match="py-spy not found"):
        Recording(1, 1.0, tmp_path / "out.txt")


BUSY = textwrap.dedent("""
    import threading, time
    def spin_other():
        while True:
            sum(range(1000))
    def spin_main():
        end = time.monotonic() + 30
        while time.monotonic() < end:
            sum(range(1000))
    threading.Thread(target=spin_other, name="other", daemon=True).start()
    print("ready", flush=True)
    spin_main()
""")


def test_a_real_recording_sees_both_busy_threads_share_the_lock(tmp_path):
    if find_py_spy() is None:
        pytest.fail("py-spy is a dev requirement: pip install -e '.[dev]'")
    child = subprocess.Popen([sys.executable, "-c", BUSY], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        time.sleep(0.5)
        recording = Recording(child.pid, 2.0, tmp_path / "gil.txt")
        try:
            out = recording.result()
        except GilProfileError as err:
            if "ermission" in str(err) or "ptrace" in str(err).lower():
                pytest.skip(f"py-spy may not read other processes here: {err}")
            raise
    finally:
        child.kill()
        child.wait()
    shares = out["gil_share_by_thread"]
    assert set(shares) == {"MainThread", "other"}
    assert shares["MainThread"] > 0.1 and shares["other"] > 0.1
    assert 0.6 < sum(shares.values()) <= 1.05  # one lock: the shares add up to at most the wall clock
    assert "spin_main (<string>)" in out["main_thread_functions"] or any(
        k.startswith("spin_main") for k in out["main_thread_functions"])


FAKE_PY_SPY = """#!/bin/sh
# Holds the lock in every sample of the duration and rate it is given, as a busy main thread does.
while [ $# -gt 0 ]; do
  case "$1" in --duration) d=$2; shift;; --rate) r=$2; shift;; --output) o=$2; shift;; esac; shift
done
echo "thread (1): MainThread;f (a.py:1) $((d * r))" > "$o"
"""


def test_shares_are_of_the_whole_seconds_py_spy_records(monkeypatch, tmp_path):
    spy = tmp_path / "py-spy"
    spy.write_text(FAKE_PY_SPY)
    spy.chmod(0o755)
    monkeypatch.setenv("PY_SPY", str(spy))
    out = Recording(1, 0.4, tmp_path / "gil.txt", rate_hz=10).result()  # py-spy records 1 s of it
    assert out["seconds"] == 1 and out["gil_share_by_thread"] == {"MainThread": 1.0}
