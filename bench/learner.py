"""Learner throughput against two anchors measured in the same run: the reference and the hardware.

    python -m bench.learner [--reference DIR] [--device cpu|cuda] [--rounds 3] [--updates 4]

One batch of 128 real transitions (cheetah-run frames, 84x84, stacks of 3) is
written to a temporary file; then, for `--rounds` rounds, separate processes
take turns on it (the order alternates from round to round, so a busy machine
weighs on both sides alike):

- `project`: NaSA-TD3 at the reference's settings and order of steps: updates/s,
  the time and FLOPs of each part of an update (critic with its TD target,
  autoencoder, actor, ensemble), and intrinsic scoring in stored order (a batch of
  consecutive transitions) and one transition at a time;
- `reference` (with `--reference DIR`, a checkout of UoA-CARES/NaSA_TD3): its
  `train_policy` + `train_predictive_model` per update and `get_intrinsic_values`
  per transition, on the same batch;
- `peak`: the matmul peak of this device with the same threads (fp32 GEMM on
  the CPU, and bf16 with a bf16 variant, the faster of BLAS and oneDNN; fp32, TF32 and BF16 on a GPU).

The summary holds the medians over rounds, the ratios to the reference (none
without --reference) and the achieved FLOP/s over the peak. FLOPs are torch's
FLOP counter's (matmuls and convolutions); SSIM and elementwise work count zero.
The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from bench import hardware
from shared.config import ALGOS

ALGO = "nasa_td3"
ACTION_DIM = 6  # cheetah-run
FRAME_STACK = 3
SINGLES = 16  # transitions scored one at a time
# The parts of an update and the agent methods that make them up (absent methods are skipped).
PARTS = {
    "critic": ("td_target", "update_critic", "update_critic_and_autoencoder"),
    "autoencoder": ("update_autoencoder",),
    "actor": ("update_actor",),
    "ensemble": ("update_ensemble",),
}
# Other agents and settings, timed on request (`--variants`): name -> (algo, config overrides).
VARIANTS = {
    "td3_ae": ("td3_ae", {}),
    "pixel_td3": ("pixel_td3", {}),
    "sac_ae": ("sac_ae", {}),
    "nasa_td3+shared_encoder_pass": ("nasa_td3", {"shared_encoder_pass": True}),
    "td3_ae+shared_encoder_pass": ("td3_ae", {"shared_encoder_pass": True}),
    "nasa_td3+fresh": ("nasa_td3", {"intrinsic_timing": "fresh"}),
    "nasa_td3+bf16": ("nasa_td3", {"pixel_precision": "bf16"}),
}
GOALS = {"update_ratio": 2.5, "update_fraction_of_peak": 0.7, "score_ratio_stored_order": 20.0}
WORKER_TIMEOUT_S = 600


# -- the batch ------------------------------------------------------------------


def rendered_stacks(count: int, seed: int = 0) -> np.ndarray:
    """`count` consecutive real frame stacks from the suite (cheetah-run, random actions)."""
    from shared import envs

    env = envs.make("cheetah-run", seed, render_quality="fast")
    rng = np.random.default_rng(seed)
    ts = env.reset()
    stacks = []
    while len(stacks) < count:
        ts = env.step(rng.uniform(-1, 1, env.action_dim))
        stacks.append(ts.obs)
        if ts.last:
            ts = env.reset()
    return np.stack(stacks)


def write_data(path: Path, batch: int, seed: int = 0) -> None:
    """The one batch both sides train on, and the transitions both sides score."""
    rng = np.random.default_rng(seed)
    stacks = rendered_stacks(2 * batch + 1, seed)
    idx = rng.integers(0, len(stacks) - 1, batch)
    np.savez(
        path,
        stacks=stacks,
        obs=stacks[idx],
        next_obs=stacks[idx + 1],
        action=rng.uniform(-1, 1, (batch, ACTION_DIM)).astype(np.float32),
        reward=rng.random(batch).astype(np.float32),
        intrinsic=rng.random(batch).astype(np.float32),
    )


def read_data(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


# -- timing ---------------------------------------------------------------------


def seconds_per_call(fn: Callable[[], object], repeats: int, device: torch.device, warmup: int = 1) -> float:
    """Mean wall-clock seconds of fn() after `warmup` untimed calls (allocator, kernels)."""
    for _ in range(warmup):
        fn()
    hardware.sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    hardware.sync(device)
    return (time.perf_counter() - start) / repeats


def even(n: int) -> int:
    """Updates come in pairs: every second one steps the actor (policy delay 2)."""
    return max(2, n + n % 2)


# -- workers (each in its own process) ------------------------------------------


def make_project_agent(algo: str, obs_shape: tuple, device: torch.device, **overrides):
    from shared.agents import make_agent
    from shared.config import agent_defaults

    config = agent_defaults(algo)
    for key, value in overrides.items():
        setattr(config, key, value)
    torch.manual_seed(0)
    return make_agent(algo, obs_shape, ACTION_DIM, config, device)


def device_batch(data: dict, device: torch.device) -> dict[str, torch.Tensor]:
    keys = ("obs", "next_obs", "action", "reward", "intrinsic")
    batch = {key: torch.from_numpy(data[key]).to(device) for key in keys}
    batch["discount"] = torch.ones(len(data["reward"]), device=device)
    return batch


def variant_figures(data: dict, device: torch.device, updates: int, repeats: int, names: list[str]) -> dict:
    """Updates/s of other agents and settings on the same batch (two warm-up updates each), and
    for those with intrinsic rewards, scoring in stored order (ms per transition)."""
    batch, rates, score_ms = device_batch(data, device), {}, {}
    stored = stored_order(*scoring_tensors(data, device))
    size = len(stored[1])
    for name in names:
        algo, overrides = VARIANTS[name]
        agent = make_project_agent(algo, tuple(data["obs"].shape[1:]), device, **overrides)
        rates[name] = 1.0 / seconds_per_call(lambda a=agent: a.update(batch), even(updates), device, warmup=2)
        if agent.uses_intrinsic:
            score_ms[name] = seconds_per_call(lambda a=agent: a.score(*stored), repeats, device) * 1000 / size
    return {"variant_updates_per_s": rates, "variant_score_ms_stored_order": score_ms}


def scoring_tensors(data: dict, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The batch's consecutive frame stacks (one more than actions) and its actions, on `device`."""
    return torch.from_numpy(data["stacks"]).to(device), torch.from_numpy(data["action"]).to(device)


def stored_order(stacks: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The batch's consecutive transitions (obs, action, next_obs): row i's next stack is row i+1's
    stack, as collect timing scores the oldest unscored rows."""
    return stacks[: len(action)], action, stacks[1 : len(action) + 1]


def project_worker(
    data: dict, device: torch.device, updates: int, score_repeats: int, algo: str, count: bool
) -> dict:
    agent = make_project_agent(algo, tuple(data["obs"].shape[1:]), device)
    batch = device_batch(data, device)
    meter = hardware.PartMeter(agent, PARTS, device)
    # Warm-up updates: two counted (the second is the first with an actor step), else one.
    with meter.attached(count=count):
        update_flops = hardware.count_flops(lambda: [agent.update(batch) for _ in range(1 + count)]) / 2
    part_flops = {k: v / 2 for k, v in meter.flops.items()}
    meter.reset()
    updates = even(updates)
    with meter.attached():
        rate = 1.0 / seconds_per_call(lambda: agent.update(batch), updates, device, warmup=0)
    result = {
        "updates_per_s": rate,
        "part_seconds_per_update": {k: v / updates for k, v in meter.seconds.items()},
    }
    if count:
        result |= {"update_flops": update_flops, "part_flops_per_update": part_flops}
    return result | project_scoring(agent, data, device, score_repeats, count)


def project_scoring(agent, data: dict, device: torch.device, repeats: int, count: bool) -> dict:
    """Stored order: the batch's consecutive transitions (row i's next stack is row i+1's stack),
    as collect timing scores the oldest unscored rows; batch_1: one transition per call."""
    stacks, action = scoring_tensors(data, device)
    stored = stored_order(stacks, action)
    size = len(action)
    # Every other transition: no next stack is another row's, as in an i.i.d. batch (fresh timing).
    unchained = (stacks[0 : 2 * size : 2], action, stacks[1 : 2 * size + 1 : 2])
    n_singles = min(SINGLES, size)
    singles = [(stacks[i : i + 1], action[i : i + 1], stacks[i + 1 : i + 2]) for i in range(n_singles)]
    ms = {
        "stored_order": seconds_per_call(lambda: agent.score(*stored), repeats, device) * 1000 / size,
        "unchained": seconds_per_call(lambda: agent.score(*unchained), repeats, device) * 1000 / size,
        "batch_1": seconds_per_call(lambda: [agent.score(*one) for one in singles], repeats, device)
        * 1000
        / n_singles,
    }
    if not count:
        return {"score_ms_per_transition": ms}
    flops = {
        "stored_order": hardware.count_flops(lambda: agent.score(*stored)) / size,
        "unchained": hardware.count_flops(lambda: agent.score(*unchained)) / size,
        "batch_1": hardware.count_flops(lambda: agent.score(*singles[0])),
    }
    return {"score_ms_per_transition": ms, "score_flops_per_transition": flops}


def reference_worker(data: dict, device: torch.device, updates: int, directory: Path, count: bool,
                     score_repeats: int) -> dict:
    from bench import reference

    torch.manual_seed(0)
    np.random.seed(0)
    agent = reference.make(directory, ACTION_DIM, FRAME_STACK, device)
    update_flops = hardware.count_flops(lambda: [reference.update(agent, data) for _ in range(1 + count)]) / 2
    updates = even(updates)
    rate = 1.0 / seconds_per_call(lambda: reference.update(agent, data), updates, device, warmup=0)
    stacks, action = data["stacks"], data["action"]

    n_singles = min(SINGLES, len(action))

    def score_singles() -> None:
        for i in range(n_singles):
            reference.score_one(agent, stacks[i], action[i], stacks[i + 1])

    result = {
        "updates_per_s": rate,
        # As many timed passes as the project's scoring gets (--score-repeats), not one.
        "score_ms_per_transition": {
            "batch_1": seconds_per_call(score_singles, score_repeats, device) * 1000 / n_singles
        },
    }
    if count:
        result["update_flops"] = update_flops
        result["score_flops_per_transition"] = {
            "batch_1": hardware.count_flops(
                lambda: reference.score_one(agent, stacks[0], action[0], stacks[1])
            )
        }
    return result


def uses_bf16(variants: list[str]) -> bool:
    """Whether a variant runs in bfloat16, so its fraction of the bf16 peak is read."""
    return any(VARIANTS[v][1].get("pixel_precision") == "bf16" for v in variants)


def peak_worker(device: torch.device, seconds: float, bf16: bool) -> dict:
    """`bf16`: on a CPU, time the bfloat16 peak too. Only asked for a bf16 variant: a CPU without
    bfloat16 units emulates it, so its two products of each size can take minutes."""
    if device.type == "cpu":
        sizes = (1024, 2048)
        peaks = {"fp32": hardware.matmul_peak_gflops(device, torch.float32, sizes, seconds)}
        if bf16:
            peaks["bf16"] = hardware.matmul_peak_gflops(device, torch.bfloat16, sizes, seconds)
        return peaks
    sizes = (4096, 8192)
    return {
        "fp32": hardware.matmul_peak_gflops(device, torch.float32, sizes, seconds, tf32=False),
        "tf32": hardware.matmul_peak_gflops(device, torch.float32, sizes, seconds, tf32=True),
        "bf16": hardware.matmul_peak_gflops(device, torch.bfloat16, sizes, seconds),
    }


def run_worker(args: argparse.Namespace) -> None:
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    from shared.device import resolve_device

    device = resolve_device(args.device)
    if args.worker == "peak":
        result = peak_worker(device, args.peak_seconds, uses_bf16(args.variants))
    else:
        data = read_data(args.data)
        if args.worker == "project":
            result = project_worker(
                data, device, args.updates, args.score_repeats, args.algo, args.count_flops
            )
            if args.variants:
                result |= variant_figures(data, device, args.updates, args.score_repeats, args.variants)
        else:
            result = reference_worker(data, device, args.updates, args.reference, args.count_flops,
                                      args.score_repeats)
    result["torch_threads"] = torch.get_num_threads()
    result["load_avg_1m"] = os.getloadavg()[0]
    print(json.dumps(result))


# -- the summary ------------------------------------------------------------------


FLOP_KEYS = ("update_flops", "part_flops_per_update", "score_flops_per_transition")


def median_tree(values: list):
    """Element-wise median of nested dicts of numbers (keys of the first; FLOP counts, which
    one round made, are taken from the round that holds them)."""
    if isinstance(values[0], dict):
        out = {key: median_tree([v[key] for v in values]) for key in values[0] if key not in FLOP_KEYS}
        counted = [v for v in values if "update_flops" in v]
        if counted:
            out |= {key: counted[0][key] for key in FLOP_KEYS if key in counted[0]}
        return out
    return statistics.median(values)


def fraction(flops: float, seconds: float, peak_gflops: float) -> float | None:
    if seconds <= 0 or peak_gflops <= 0:
        return None
    return flops / seconds / (peak_gflops * 1e9)


def summarize(rounds: list[dict], device: str, batch: int) -> dict:
    """The medians over rounds, ratios to the reference where it ran, and fractions of the peak.

    `rounds`: one dict per round with `project`, `peak` and optionally `reference`, each a
    worker's result."""
    project = median_tree([r["project"] for r in rounds])
    peaks = median_tree([r["peak"] for r in rounds])
    peak = peaks["fp32"]
    score_ms, score_flops = project["score_ms_per_transition"], project["score_flops_per_transition"]
    parts_s, parts_f = project["part_seconds_per_update"], project["part_flops_per_update"]
    out: dict = {
        "device": device,
        "batch": batch,
        "rounds": len(rounds),
        "updates_per_s": round(project["updates_per_s"], 4),
        "score_ms_per_transition": {k: round(v, 3) for k, v in score_ms.items()},
        "sgemm_peak_gflops": round(peak, 1),
        "update_gflop": round(project["update_flops"] / 1e9, 2),
        "update_fraction_of_peak": _round(
            fraction(project["update_flops"], 1.0 / project["updates_per_s"], peak)
        ),
        "part_seconds_per_update": {k: round(v, 4) for k, v in parts_s.items()},
        "part_gflop_per_update": {k: round(v / 1e9, 2) for k, v in parts_f.items()},
        "part_fraction_of_peak": {k: _round(fraction(parts_f[k], parts_s[k], peak)) for k in parts_s},
        "score_gflop_per_transition": {k: round(v / 1e9, 3) for k, v in score_flops.items()},
        "score_fraction_of_peak": {
            k: _round(fraction(score_flops[k], score_ms[k] / 1000, peak)) for k in score_ms
        },
    }
    formats = [name for name in ("fp32", "tf32", "bf16") if name in peaks]
    if len(formats) > 1:
        out["matmul_peak_gflops"] = {k: round(peaks[k], 1) for k in formats}
        for name in formats[1:]:
            out[f"update_fraction_of_{name}_peak"] = _round(
                fraction(project["update_flops"], 1.0 / project["updates_per_s"], peaks[name])
            )
    if "variant_updates_per_s" in project:
        out["variant_updates_per_s"] = {k: round(v, 4) for k, v in project["variant_updates_per_s"].items()}
    if project.get("variant_score_ms_stored_order"):
        out["variant_score_ms_stored_order"] = {
            k: round(v, 3) for k, v in project["variant_score_ms_stored_order"].items()
        }
    if all("reference" in r for r in rounds):
        out |= reference_figures([r["reference"] for r in rounds], project, peak)
    loads = [r["project"].get("load_avg_1m", 0.0) for r in rounds]
    if max(loads) > (os.cpu_count() or 1):
        out["warning"] = (
            f"busy machine: 1-minute load average up to {max(loads):.1f} on {os.cpu_count()} cores; "
            "the rates and ratios move with the share of the cores each process got"
        )
    out["goals_met"] = {
        name: (out[name] >= goal if out.get(name) is not None else None) for name, goal in GOALS.items()
    }
    out["per_round"] = {
        "updates_per_s": [round(r["project"]["updates_per_s"], 4) for r in rounds],
        "reference_updates_per_s": [
            round(r["reference"]["updates_per_s"], 4) for r in rounds if "reference" in r
        ],
        "sgemm_peak_gflops": [round(r["peak"]["fp32"], 1) for r in rounds],
        "load_avg_1m": [round(r["project"].get("load_avg_1m", 0.0), 2) for r in rounds],
    }
    return out


def reference_figures(references: list[dict], project: dict, peak: float) -> dict:
    ref = median_tree(references)
    ref_score_ms = ref["score_ms_per_transition"]["batch_1"]
    score_ms = project["score_ms_per_transition"]
    return {
        "reference_updates_per_s": round(ref["updates_per_s"], 4),
        "reference_score_ms_per_transition": round(ref_score_ms, 3),
        "reference_update_gflop": round(ref["update_flops"] / 1e9, 2),
        "reference_update_fraction_of_peak": _round(
            fraction(ref["update_flops"], 1.0 / ref["updates_per_s"], peak)
        ),
        "update_ratio": round(project["updates_per_s"] / ref["updates_per_s"], 3),
        **(
            {
                "variant_update_ratio": {
                    k: round(v / ref["updates_per_s"], 3) for k, v in project["variant_updates_per_s"].items()
                }
            }
            if "variant_updates_per_s" in project
            else {}
        ),  # fmt: skip
        "score_ratio_stored_order": round(ref_score_ms / score_ms["stored_order"], 2),
        "score_ratio_batch_1": round(ref_score_ms / score_ms["batch_1"], 2),
        **(
            {
                "variant_score_ratio_stored_order": {
                    k: round(ref_score_ms / v, 2) for k, v in project["variant_score_ms_stored_order"].items()
                }
            }
            if project.get("variant_score_ms_stored_order")
            else {}
        ),  # fmt: skip
    }


def _round(value: float | None, digits: int = 3) -> float | None:
    return None if value is None else round(value, digits)


# -- the orchestrator ---------------------------------------------------------------


def worker_command(args: argparse.Namespace, side: str, data: Path, count: bool) -> list[str]:
    cmd = [
        sys.executable,
        "-m",
        "bench.learner",
        "--worker",
        side,
        "--data",
        str(data),
        "--device",
        args.device,
        "--threads",
        str(args.threads),
        "--updates",
        str(args.updates),
        "--score-repeats",
        str(args.score_repeats),
        "--peak-seconds",
        str(args.peak_seconds),
        "--algo",
        args.algo,
    ]
    if args.reference is not None:
        cmd += ["--reference", str(args.reference)]
    if args.variants and side in ("project", "peak"):
        cmd += ["--variants", ",".join(args.variants)]
    return cmd + (["--count-flops"] if count else [])


def call_worker(cmd: list[str]) -> dict:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=WORKER_TIMEOUT_S)
    if proc.returncode != 0:
        raise RuntimeError(f"worker {cmd[4]} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_rounds(args: argparse.Namespace, data: Path) -> list[dict]:
    sides = ["project", "peak"] + (["reference"] if args.reference is not None else [])
    rounds = []
    for r in range(args.rounds):
        order = sides if r % 2 == 0 else sides[::-1]
        results = {}
        for side in order:
            start = time.perf_counter()
            results[side] = call_worker(worker_command(args, side, data, count=r == 0))
            print(
                f"round {r + 1}/{args.rounds} {side:9s} {time.perf_counter() - start:5.1f} s  "
                f"{_brief(side, results[side])}",
                flush=True,
            )
        rounds.append(results)
    return rounds


def _brief(side: str, result: dict) -> str:
    if side == "peak":
        return "matmul GFLOP/s " + ", ".join(
            f"{k} {v:.0f}" for k, v in result.items() if k in ("fp32", "tf32", "bf16")
        )
    score = ", ".join(f"{k} {v:.2f} ms" for k, v in result["score_ms_per_transition"].items())
    return f"{result['updates_per_s']:.3f} updates/s; scoring per transition: {score}"


def variant_list(text: str) -> list[str]:
    names = list(VARIANTS) if text == "all" else [n for n in text.split(",") if n]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown variant(s) {unknown}; choose from {', '.join(VARIANTS)} or all"
        )
    return names


def positive(kind: type) -> Callable[[str], float]:
    """An argparse type: a number of `kind` above 0."""

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be above 0, got {text!r}")
        return value

    return parse


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", type=Path, default=None, help="a checkout of UoA-CARES/NaSA_TD3")
    p.add_argument("--device", default="cpu")
    p.add_argument("--batch", type=positive(int), default=128)
    p.add_argument("--rounds", type=positive(int), default=3)
    p.add_argument("--updates", type=positive(int), default=4, help="timed updates per process (even)")
    p.add_argument("--score-repeats", type=positive(int), default=3)
    p.add_argument("--peak-seconds", type=positive(float), default=1.0, help="timing per matmul size")
    p.add_argument(
        "--threads", type=int, default=0, help="torch threads (0: torch's default, as the learner)"
    )
    p.add_argument("--algo", default=ALGO, choices=ALGOS,
                   help="the project's agent (the reference is NaSA-TD3)")
    p.add_argument(
        "--variants",
        type=variant_list,
        default=[],
        help=f"other agents/settings to time too, comma-separated, or all: {', '.join(VARIANTS)}",
    )
    p.add_argument("--worker", choices=("project", "reference", "peak"), help=argparse.SUPPRESS)
    p.add_argument("--data", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--count-flops", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.worker:
        run_worker(args)
        return
    from bench import reference
    from shared.device import DeviceError, resolve_device

    try:  # a bad directory or device fails here, in one line, before any rendering
        if args.reference is not None:
            reference.load_class(args.reference)
        device = resolve_device(args.device)
    except (reference.ReferenceError, DeviceError) as err:
        print(f"bench.learner: {err}", file=sys.stderr)
        sys.exit(2)
    info = hardware.machine(device)
    if args.threads > 0:
        info["torch_threads"] = args.threads
    print(f"machine: {info}; load {os.getloadavg()[0]:.2f}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-learner-") as tmp:
        data = Path(tmp) / "batch.npz"
        write_data(data, args.batch)
        rounds = run_rounds(args, data)
    summary = summarize(rounds, str(device), args.batch)
    summary["machine"] = info
    summary["date_utc"] = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    summary["algo"] = args.algo
    print(json.dumps(summary))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.learner"):
        main()
