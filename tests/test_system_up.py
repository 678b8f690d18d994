"""`nasa up` as a user runs it: first line names the preset, `nasa status` reads it, Ctrl-C stops all."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from system_harness import REPO, TINY

from nasa.up import free_port


def children_of(pid: int) -> list[int]:
    """Processes started under launcher `pid` (services carry NASA_PARENT_PID)."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            env = (proc / "environ").read_bytes().split(b"\0")
            state = (proc / "stat").read_text().split(")")[-1].split()[0]
        except OSError:
            continue
        if f"NASA_PARENT_PID={pid}".encode() in env and state != "Z":
            found.append(int(proc.name))
    return found


@pytest.mark.timeout(240)
def test_nasa_up_runs_reports_and_stops_on_ctrl_c(tmp_path):
    port = free_port()
    cmd = [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--actors", "1",
           "--steps", "100000", "--device", "cpu", "--data", str(tmp_path / "run"), "--port", str(port),
           "--router-port", "0", "--learner-threads", "1", "--logs", "--", *TINY]
    up = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        first = up.stdout.readline()
        assert first.startswith("nasa up: preset cpu-small (auto: no GPU"), first
        assert f"http://127.0.0.1:{port}/status" in up.stdout.readline()
        deadline = time.monotonic() + 150
        status = None
        while time.monotonic() < deadline:
            url = f"http://127.0.0.1:{port}/status"
            out = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--url", url],
                                 cwd=REPO, capture_output=True, text=True)
            if out.returncode == 0:
                status = json.loads(out.stdout)
                if status["actors"] and status["env_steps"] > 0:
                    break
            time.sleep(0.5)
        assert status is not None and status["actors"] and status["env_steps"] > 0, status
        assert status["task"] == "cartpole-balance" and status["algo"] == "nasa_td3"
        kids = children_of(up.pid)
        assert len(kids) == 4  # replay, learner, evaluator, one actor
        up.send_signal(signal.SIGINT)
        rest, _ = up.communicate(timeout=90)
        assert up.returncode == 0, rest
        assert "nasa up: stopped" in rest
        assert [p for p in kids if Path(f"/proc/{p}").exists() and p in children_of(up.pid)] == []
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert children_of(up.pid) == []
