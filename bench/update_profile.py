"""Where one learner update's time goes: the wall clock against the host's and the device's time.

    python -m bench.update_profile [--device cuda] [--updates 100] [--profiled 10]
        [--batches 256,512]

The project's NaSA-TD3 update at the paper's settings, on bench.learner's batch of real
cheetah-run frames (batch 128), with nothing attached (bench.learner's part meter synchronises
between parts). It reports:

- updates/s eager with default settings and, on CUDA, each setting added in turn:
  `cudnn.benchmark`, TF32 matmuls, bf16 pixel networks (`--pixel-precision bf16`), and the
  first two at larger batches (the data repeated); last, the update replayed as captured CUDA
  graphs (`agent.cuda_graph`, with cudnn.benchmark and TF32: `cuda_graph_updates_per_s`);
- from torch's profiler over `--profiled` updates: the host's time in torch's operators, the
  device's busy time (the kernels' own time) and the kernel launches, each per update; on
  CUDA for the graphed update too (keys `cuda_graph_...`, with `cuda_graph_capture`: `ok` or
  why the capture failed and the agent stayed eager).

An update whose wall time is close to the host's time and well above the device's busy time is
bound by Python and launches: fewer, larger kernels or a captured CUDA graph are the lever, not
faster arithmetic. One whose wall time is close to the device's busy time is bound by its kernels.
The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import torch

from bench import hardware
from bench import learner as bench_learner
from shared.agents.base import Agent
from shared.device import DeviceError, resolve_device

LAUNCHES = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx")


def summarize_profile(events: Iterable, updates: int) -> dict:
    """Per update, from torch profiler events: the host's self time in operators, the device's
    busy time (kernels and device copies, each counted once) and the kernel launches."""
    host_us = device_us = launches = 0.0
    for e in events:
        if e.device_type == torch.autograd.DeviceType.CUDA:
            device_us += e.time_range.elapsed_us()
        else:
            host_us += e.self_cpu_time_total
            launches += e.name in LAUNCHES
    return {
        "host_s_per_update": host_us / 1e6 / updates,
        "device_busy_s_per_update": device_us / 1e6 / updates if device_us else None,
        "kernel_launches_per_update": launches / updates,
    }


@contextmanager
def cuda_settings(cudnn_benchmark: bool, tf32: bool) -> Iterator[None]:
    """cudnn.benchmark and TF32 matmuls set for the block (process-wide), restored afterwards."""
    before = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = cudnn_benchmark
    try:
        with hardware.matmul_precision(torch.float32, tf32):
            yield
    finally:
        torch.backends.cudnn.benchmark = before


# A graphed agent's first updates: eager ones (shared.agents.cuda_graph: twice the update's period
# of two), then one capture per phase, with room to spare.
GRAPH_WARMUP = 8


def fresh_agent(data: dict, device: torch.device, **overrides: object) -> Agent:
    """A new NaSA-TD3 agent (bench.learner's, seeded) for the batch's frame stacks."""
    shape = tuple(data["obs"].shape[1:])
    return bench_learner.make_project_agent(bench_learner.ALGO, shape, device, **overrides)


def updates_per_s(
    data: dict, device: torch.device, updates: int, batch_repeat: int = 1, **overrides: object
) -> float:
    """A fresh agent's updates/s on the batch (repeated `batch_repeat` times), after warm-up (with
    `cuda_graph`, after its graphs are captured)."""
    agent = fresh_agent(data, device, **overrides)
    batch = {k: torch.cat([v] * batch_repeat) for k, v in bench_learner.device_batch(data, device).items()}
    seconds = bench_learner.seconds_per_call(
        lambda: agent.update(batch), bench_learner.even(updates), device, warmup=warmup_updates(overrides)
    )
    return 1.0 / seconds


def warmup_updates(overrides: dict) -> int:
    """Updates before timing: a graphed agent's eager ones and its captures come first."""
    return GRAPH_WARMUP if overrides.get("cuda_graph") else 4


def profile(data: dict, device: torch.device, updates: int, **overrides: object) -> dict:
    agent = fresh_agent(data, device, **overrides)
    batch = bench_learner.device_batch(data, device)
    for _ in range(warmup_updates(overrides)):
        agent.update(batch)
    hardware.sync(device)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    start = time.perf_counter()
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(updates):
            agent.update(batch)
        hardware.sync(device)
    wall = (time.perf_counter() - start) / updates
    out = {"profiled_wall_s_per_update": wall, **summarize_profile(prof.events(), updates)}
    if overrides.get("cuda_graph"):  # a failed capture leaves the agent eager: say so
        out["capture"] = agent._graphed.failed or "ok"
    return out


def rates(data: dict, device: torch.device, updates: int, batches: list[int]) -> dict[str, float]:
    out = {"default": updates_per_s(data, device, updates)}
    if device.type != "cuda":
        return out
    with cuda_settings(cudnn_benchmark=True, tf32=False):
        out["cudnn_benchmark"] = updates_per_s(data, device, updates)
    with cuda_settings(cudnn_benchmark=True, tf32=True):
        out["cudnn_benchmark+tf32"] = updates_per_s(data, device, updates)
        out["cudnn_benchmark+tf32+bf16"] = updates_per_s(data, device, updates, pixel_precision="bf16")
        base = len(data["reward"])
        for size in batches:
            out[f"cudnn_benchmark+tf32 batch {size}"] = updates_per_s(data, device, updates, size // base)
    return out


def graphed(data: dict, device: torch.device, updates: int, profiled: int) -> dict:
    """The update replayed as CUDA graphs (`agent.cuda_graph`): updates/s with cudnn.benchmark and
    TF32, and its profile, under `cuda_graph_` keys; or the error that stopped them."""
    try:
        with cuda_settings(cudnn_benchmark=True, tf32=True):
            rate = updates_per_s(data, device, updates, cuda_graph=True)
        profiled_graph = profile(data, device, profiled, cuda_graph=True)
        return {"cuda_graph_updates_per_s": round(rate, 2)} | {
            f"cuda_graph_{key}": value for key, value in profiled_graph.items()}
    except RuntimeError as err:
        return {"cuda_graph_error": f"{type(err).__name__}: {err}"[:400]}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--updates", type=int, default=100, help="timed updates per setting")
    p.add_argument("--profiled", type=int, default=10, help="updates under the profiler")
    p.add_argument("--batches", default="256,512", help="larger batches (multiples of 128) on CUDA")
    args = p.parse_args(argv)
    try:
        args.batches = [int(b) for b in args.batches.split(",") if b.strip()]
    except ValueError:
        p.error(f"--batches: comma-separated integers, got {args.batches!r}")
    if min(args.updates, args.profiled) < 1 or any(b < 128 or b % 128 for b in args.batches):
        p.error("--updates and --profiled must be >= 1; --batches multiples of 128")
    # As bench.learner's workers and the learner service resolve it: on the CPU that also keeps
    # freed memory for reuse, which moves a CPU update's time.
    try:
        args.device = resolve_device(args.device)
    except DeviceError as err:
        p.error(f"--device: {err}")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    device = args.device
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "batch.npz"
        bench_learner.write_data(path, 128)
        data = bench_learner.read_data(path)
    result: dict = {"device": str(device), "machine": hardware.machine(device), "batch": 128}
    result["updates_per_s"] = {
        k: round(v, 2) for k, v in rates(data, device, args.updates, args.batches).items()
    }
    print(f"updates/s: {result['updates_per_s']}", flush=True)
    result |= profile(data, device, args.profiled)
    if device.type == "cuda":  # last: the eager figures stand even if a capture breaks the device
        result |= graphed(data, device, args.updates, args.profiled)
    print(json.dumps({k: round(v, 5) if isinstance(v, float) else v for k, v in result.items()}))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.update_profile"):
        main()
