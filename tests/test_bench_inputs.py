"""A benchmark given an unknown task or algorithm refuses it as a bad flag: one line, exit 2, at
once, not after starting services that refuse it while the benchmark waits for them."""

from __future__ import annotations

import subprocess
import sys

import pytest
from system_harness import REPO


@pytest.mark.parametrize("name", ["system", "dashboard", "learning", "up_profile", "replay", "render"])
def test_an_unknown_task_is_refused_at_once(name):
    flags = {"replay": ["--tasks", "cartpole-balance,cartpole-sideways"],
             "render": ["--tasks", "cartpole-balance", "cartpole-sideways"]}
    flag = flags.get(name, ["--task", "cartpole-sideways"])  # the bad one after a good one
    out = subprocess.run([sys.executable, "-m", f"bench.{name}", *flag], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stdout == ""
    last = out.stderr.splitlines()[-1]
    assert f"argument {flag[0]}: unknown task 'cartpole-sideways'; valid tasks are: " in last
    assert "cartpole-balance" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("name", ["system", "dashboard"])
def test_an_unknown_algorithm_is_refused_at_once(name):
    out = subprocess.run([sys.executable, "-m", f"bench.{name}", "--algo", "td4"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "argument --algo: invalid choice: 'td4'" in out.stderr
    assert "Traceback" not in out.stderr


def test_bench_up_profile_says_why_nasa_up_refused_its_flags():
    out = subprocess.run([sys.executable, "-m", "bench.up_profile", "--task", "cartpole-balance", "--",
                          "--no-such-flag"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr and out.stdout.strip() == ""
    assert out.stderr.strip().splitlines() == [
        "bench.up_profile: nasa up ended (exit 2) before its first update: nasa up: error: Unrecognized "
        "options: --no-such-flag (`nasa up --help` lists its flags)"]
