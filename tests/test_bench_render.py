"""bench.render: the render qualities' cost and frames; --gl-threads: the rasterizer's threads compared in
alternating processes, and the frames compared too (the same pixels, drawn either way)."""

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


def test_qualities_report_cost_and_difference_from_paper():
    out = subprocess.run(
        [sys.executable, "-m", "bench.render", "--frames", "10", "--tasks", "cartpole-balance"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout.strip().splitlines()[-1])["tasks"]["cartpole-balance"]
    for quality in ("paper", "fast", "plain"):
        assert row[f"{quality}_steps_per_s"] > 0 and row[f"{quality}_cpu_ms_per_step"] > 0
    for quality in ("fast", "plain"):
        assert 0 < row[f"{quality}_mean_abs_diff"] < 20
