"""`nasa up --zenoh-auth` end to end: every service logs in under its role and trains through the
ACL, and the learner's controls answer only with the bearer token (the stop one ends the run)."""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from system_harness import REPO, TINY

from nasa.up import free_port
from shared.zenoh_auth import ACL_FILE, USERS_FILE

TOKEN = "a-test-token"


def wait_for(url: str, up: subprocess.Popen, pred, timeout: float = 150.0) -> dict:  # noqa: ANN001
    deadline, last = time.monotonic() + timeout, None
    while time.monotonic() < deadline and up.poll() is None:
        try:
            last = httpx.get(url, timeout=5.0).json()
            if pred(last):
                return last
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise AssertionError(f"timed out; last status {last}; nasa up exited {up.poll()}")


@pytest.mark.timeout(300)
def test_a_run_with_logins_acl_and_token(tmp_path: Path) -> None:
    data, auth, port = tmp_path / "run", tmp_path / "auth", free_port()
    cmd = [sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-balance", "--actors", "1",
           "--steps", "100000", "--device", "cpu", "--data", str(data), "--port", str(port),
           "--router-port", "0", "--learner-threads", "1", "--logs", "--zenoh-auth", str(auth), *TINY]
    env = {**os.environ, "PYTHONPATH": str(REPO), "NASA_API_TOKEN": TOKEN}
    up = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        # Updates need replay samples, weights reach the actor, the actor's token reaches the learner:
        # every route of a training run passed the router's ACL.
        status = wait_for(f"{base}/status", up, lambda s: s["updates"] > 0 and s["actors"]
                          and s["actors"][0]["alive"] and s["actors"][0]["policy_version"] > 0)
        assert status["invalid_messages"] == 0
        assert stat.S_IMODE((auth / USERS_FILE).stat().st_mode) == 0o600 and (auth / ACL_FILE).exists()
        checkpoint = data / "learner" / "checkpoint.pt"
        assert not checkpoint.exists()  # cpu-small checkpoints every 5,000 env steps
        assert httpx.post(f"{base}/control/checkpoint").status_code == 401
        wrong = {"Authorization": "Bearer wrong"}
        assert httpx.post(f"{base}/control/stop", headers=wrong).status_code == 401
        assert up.poll() is None
        auth_header = {"Authorization": f"Bearer {TOKEN}"}
        assert httpx.post(f"{base}/control/checkpoint", headers=auth_header).status_code == 202
        while not checkpoint.exists() and up.poll() is None:
            time.sleep(0.2)
        assert checkpoint.exists()
        assert httpx.post(f"{base}/control/stop", headers=auth_header).status_code == 202
        out, _ = up.communicate(timeout=120)
        assert up.returncode == 0, out
        # Ended by the Stop message: the run is done, not a service that died.
        assert re.search(r"stopping in order \(the run is done \((learner|replay) finished\)\)", out), out
        assert "stop message: stop requested over HTTP" in (data / "logs" / "learner.log").read_text()
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
