"""Learner throughput: updates/s of every agent at batch 128 and intrinsic scoring time.

Reference settings (84x84x9 stacks, the reference's widths) on the current device.
The reference implementation's figures on this 2-core CPU (../shared/DESIGN.md):
0.38 updates/s at batch 128 and 20-25 ms to score one transition.

    python -m bench.learner [--device cpu] [--updates 6] [--batch 128]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable

import numpy as np
import torch

from shared import envs, intrinsic
from shared.agents import make_agent
from shared.config import ALGOS, agent_defaults
from shared.device import resolve_device

REFERENCE_UPDATES_PER_S = 0.38
REFERENCE_SCORE_MS = 22.5  # midpoint of 20-25 ms


def rendered_stacks(count: int, seed: int = 0) -> np.ndarray:
    """Real frame stacks from the suite (cheetah-run, random actions)."""
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


def make_batch(stacks: np.ndarray, batch: int, action_dim: int, device: torch.device, rng) -> dict:
    idx = rng.integers(0, len(stacks) - 1, batch)
    return {
        "obs": torch.from_numpy(stacks[idx]).to(device),
        "next_obs": torch.from_numpy(stacks[idx + 1]).to(device),
        "action": torch.from_numpy(rng.uniform(-1, 1, (batch, action_dim)).astype(np.float32)).to(device),
        "reward": torch.from_numpy(rng.random(batch).astype(np.float32)).to(device),
        "discount": torch.ones(batch, device=device),
        "intrinsic": torch.from_numpy(rng.random(batch).astype(np.float32)).to(device),
    }


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def seconds_per_call(fn: Callable[[], object], repeats: int, device: torch.device, warmup: int = 1) -> float:
    """Mean wall-clock seconds of fn() after `warmup` untimed calls (allocator, kernels)."""
    for _ in range(warmup):
        fn()
    sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    sync(device)
    return (time.perf_counter() - start) / repeats


def time_updates(algo: str, batch: dict, updates: int, device: torch.device, **overrides) -> float:
    config = agent_defaults(algo)
    for key, value in overrides.items():
        setattr(config, key, value)
    torch.manual_seed(0)
    agent = make_agent(algo, (9, 84, 84), batch["action"].shape[1], config, device)
    # Two warm-up updates: the second is the first with an actor step.
    return 1.0 / seconds_per_call(lambda: agent.update(batch), updates, device, warmup=2)


def scoring_batches(stacks: np.ndarray, batch: int, action_dim: int, device: torch.device, rng) -> dict:
    """Two batches of real transitions to score.

    `stored_order`: consecutive transitions, as collect timing scores them from the
    replay (the oldest unscored rows; each next stack is the following row's stack).
    `unchained`: every other transition, so that no next stack is in the batch, as
    in an i.i.d. training batch (fresh timing)."""
    action = torch.from_numpy(rng.uniform(-1, 1, (batch, action_dim)).astype(np.float32)).to(device)
    stacks_t = torch.from_numpy(stacks).to(device)
    return {
        "stored_order": (stacks_t[:batch], action, stacks_t[1 : batch + 1]),
        "unchained": (stacks_t[0 : 2 * batch : 2], action, stacks_t[1 : 2 * batch + 1 : 2]),
    }


def time_scoring(
    batches: dict, repeats: int, device: torch.device
) -> tuple[dict[str, float], dict[str, float]]:
    """Milliseconds per transition to score novelty + surprise in each batch and one
    transition at a time (`batch_1`: the single-process trainer, like the reference),
    and the milliseconds per batch of each part (one encoder pass, the decoder, SSIM,
    ensemble)."""
    torch.manual_seed(0)
    obs, action, next_obs = batches["unchained"]
    agent = make_agent("nasa_td3", tuple(obs.shape[1:]), action.shape[1], agent_defaults("nasa_td3"), device)

    def ms(fn: Callable[[], object]) -> float:
        return seconds_per_call(fn, repeats, device) * 1000

    per_transition = {name: ms(lambda b=b: agent.score(*b)) / len(b[0]) for name, b in batches.items()}
    singles = [(o[None], a[None], n[None]) for o, a, n in zip(obs[:32], action, next_obs, strict=False)]
    per_transition["batch_1"] = ms(lambda: [agent.score(*one) for one in singles]) / len(singles)
    with torch.no_grad():
        z = agent.encoder(obs)
        reconstruction = agent.decoder(z)
        parts = {
            "encoder_pass": ms(lambda: agent.encoder(obs)),
            "decoder_pass": ms(lambda: agent.decoder(z)),
            "ssim": ms(lambda: intrinsic.novelty(obs, reconstruction)),
            "ensemble": ms(lambda: agent.ensemble(z, action)),
        }
    return per_transition, {k: round(v, 1) for k, v in parts.items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--updates", type=int, default=6)
    parser.add_argument("--score-repeats", type=int, default=5)
    args = parser.parse_args()
    device = resolve_device(args.device)
    rng = np.random.default_rng(0)
    stacks = rendered_stacks(args.batch * 2 + 1)
    batch = make_batch(stacks, args.batch, 6, device, rng)
    print(f"device {device}, torch threads {torch.get_num_threads()}, load {os.getloadavg()[0]:.2f}")

    result: dict = {"device": str(device), "batch": args.batch, "updates_per_s": {}}
    for algo in ALGOS:
        rate = time_updates(algo, batch, args.updates, device)
        result["updates_per_s"][algo] = round(rate, 3)
        print(f"{algo:10s} {rate:6.3f} updates/s  ({rate / REFERENCE_UPDATES_PER_S:.2f}x the reference)")
    for algo in ("nasa_td3", "td3_ae"):
        rate = time_updates(algo, batch, args.updates, device, shared_encoder_pass=True)
        result["updates_per_s"][f"{algo}+shared_encoder_pass"] = round(rate, 3)
        print(f"{algo:10s} {rate:6.3f} updates/s with shared_encoder_pass (not the reference's order)")
    rate = time_updates("nasa_td3", batch, args.updates, device, intrinsic_timing="fresh")
    result["updates_per_s"]["nasa_td3+fresh"] = round(rate, 3)
    print(f"nasa_td3   {rate:6.3f} updates/s with intrinsic_timing fresh (the batch rescored each update)")
    to_score = scoring_batches(stacks, args.batch, 6, device, rng)
    score_ms, parts = time_scoring(to_score, args.score_repeats, device)
    for name, value in score_ms.items():
        size = 1 if name == "batch_1" else args.batch
        print(f"scoring, {name}: {value:.3f} ms per transition in batches of {size} "
              f"({REFERENCE_SCORE_MS / value:.1f}x the reference)")
    print(f"scoring parts, ms per batch (unchained: 2 encoder passes + the rest): {parts}")
    result["score_ms_per_transition"] = {k: round(v, 3) for k, v in score_ms.items()}
    result["score_parts_ms_per_batch"] = parts
    result["speedup_vs_reference"] = {
        "nasa_td3_updates": round(result["updates_per_s"]["nasa_td3"] / REFERENCE_UPDATES_PER_S, 2),
        "scoring": {k: round(REFERENCE_SCORE_MS / v, 1) for k, v in score_ms.items()},
    }
    result["reference"] = {"updates_per_s": REFERENCE_UPDATES_PER_S, "score_ms": REFERENCE_SCORE_MS}
    result["load_avg_1m"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
