"""bench.update_profile: the profiler's events summed per update without double counting, the
CUDA settings restored, bad arguments refused, and a real run on the CPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from bench import update_profile

ROOT = Path(__file__).resolve().parents[1]
CPU, CUDA = torch.autograd.DeviceType.CPU, torch.autograd.DeviceType.CUDA


def event(name: str, device, self_cpu_us: float = 0.0, elapsed_us: float = 0.0) -> SimpleNamespace:
    return SimpleNamespace(name=name, device_type=device, self_cpu_time_total=self_cpu_us,
                           time_range=SimpleNamespace(elapsed_us=lambda: elapsed_us))  # fmt: skip


def test_the_summary_counts_each_kernel_once_and_the_host_in_self_time():
    events = [
        event("aten::convolution", CPU, self_cpu_us=300.0),
        event("cudaLaunchKernel", CPU, self_cpu_us=20.0),
        event("cudaLaunchKernel", CPU, self_cpu_us=20.0),
        event("cuLaunchKernel", CPU, self_cpu_us=10.0),
        event("implicit_gemm_kernel", CUDA, elapsed_us=500.0),
        event("elementwise_kernel", CUDA, elapsed_us=100.0),
    ]
    summary = update_profile.summarize_profile(events, updates=2)
    assert summary["host_s_per_update"] == pytest.approx(350e-6 / 2)
    assert summary["device_busy_s_per_update"] == pytest.approx(600e-6 / 2)
    assert summary["kernel_launches_per_update"] == 1.5


def test_without_device_events_the_device_time_is_none():
    summary = update_profile.summarize_profile([event("aten::mm", CPU, self_cpu_us=40.0)], updates=1)
    assert summary["device_busy_s_per_update"] is None and summary["kernel_launches_per_update"] == 0


def test_cuda_settings_are_restored_after_the_block_even_on_error():
    before = torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32
    with pytest.raises(RuntimeError):
        with update_profile.cuda_settings(cudnn_benchmark=not before[0], tf32=not before[1]):
            assert torch.backends.cudnn.benchmark is (not before[0])
            raise RuntimeError("boom")
    assert (torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32) == before


@pytest.mark.parametrize("args", [["--batches", "100"], ["--batches", "x"], ["--updates", "0"]])
def test_bad_arguments_are_refused_with_exit_2(args):
    with pytest.raises(SystemExit) as exit_info:
        update_profile.parse_args(["--device", "cpu", *args])
    assert exit_info.value.code == 2


def test_a_real_run_on_the_cpu_ends_with_one_json_line():
    result = subprocess.run(
        [sys.executable, "-m", "bench.update_profile", "--device", "cpu", "--updates", "2",
         "--profiled", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=600, env={**os.environ, "MUJOCO_GL": "egl"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert out["device"] == "cpu" and list(out["updates_per_s"]) == ["default"]
    assert out["updates_per_s"]["default"] > 0
    # On the CPU the host's time is the update: most of the wall time, and no device time.
    wall = out["profiled_wall_s_per_update"]
    assert 0.5 * wall < out["host_s_per_update"] <= 1.05 * wall
    assert out["device_busy_s_per_update"] is None and out["kernel_launches_per_update"] == 0


def test_a_graphed_measurement_that_fails_reports_its_error_and_nothing_else(monkeypatch):
    why = "CUDA error: operation not permitted when stream is capturing"

    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError(why)

    monkeypatch.setattr(update_profile, "updates_per_s", broken)
    out = update_profile.graphed({}, torch.device("cpu"), updates=1, profiled=1)
    assert out == {"cuda_graph_error": f"RuntimeError: {why}"}


def test_the_device_is_resolved_as_the_learner_resolves_it(monkeypatch):
    # On the CPU that keeps freed memory for reuse, as bench.learner's workers and the learner do.
    import shared.device

    kept = []
    monkeypatch.setattr(shared.device, "keep_freed_memory", lambda: kept.append(True) or True)
    assert update_profile.parse_args(["--device", "cpu"]).device == torch.device("cpu") and kept


@pytest.mark.parametrize("device", ["tpu", "cuda:99"])
def test_a_device_that_is_not_here_is_refused_with_exit_2(device, capsys):
    with pytest.raises(SystemExit) as exit_info:
        update_profile.parse_args(["--device", device])
    assert exit_info.value.code == 2 and "--device" in capsys.readouterr().err
