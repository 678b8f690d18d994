"""bench.render --gl-threads: the rasterizer's threads compared in alternating processes, and the frames
compared too (the same pixels, drawn either way)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_gl_threads_reports_each_setting_and_the_same_frames():
    out = subprocess.run(
        [sys.executable, "-m", "bench.render", "--gl-threads", "--frames", "20", "--rounds", "2",
         "--tasks", "cartpole-balance"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    row = result["tasks"]["cartpole-balance"]
    assert row["same_frames"] is True
    for name in ("caller_thread", "thread_per_core"):
        assert row[f"{name}_wall_ms"] > 0 and row[f"{name}_cpu_ms"] > 0
    assert result["rounds"] == 2 and result["frames"] == 20
