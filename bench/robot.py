"""The robot bridge's cost: the gripper stand-in stepped through a bridge process against in-process.

Both step `ValveSim` with the same seed and actions ('fast' render quality), an episode each in
turn, so a load change on the machine hits both alike. The bridge runs as its own process
(`python -m services.robot_bridge`) behind a Zenoh router on loopback, and the client is
`BridgeEnv`, as an actor holds it. The bridge's added latency per step is the client's round
trip minus the environment time the bridge reports for that step. The real robot's budget is
about 0.8 s per step, so the bridge must never be the slow part.

    python -m bench.robot [--episodes 6]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from nasa.up import free_port
from services.robot_bridge.client import BridgeEnv
from shared import wire
from shared.gripper.sim import EPISODE_STEPS, ValveSim
from shared.service import followed
from shared.zenoh_session import open_client, open_router, token_up

TASK = "gripper-valve_reset"


def episode(env, actions: np.ndarray) -> tuple[list[float], list[float]]:
    """One episode (reset excluded from the times): each step's wall time, and its env time."""
    env.reset()
    walls, env_times = [], []
    for action in actions:
        start = time.perf_counter()
        _, _, _, last = env.step(action)
        wall = time.perf_counter() - start
        walls.append(wall)
        env_times.append(getattr(env, "info", {}).get("env_s", wall))
        if last:
            break
    return walls, env_times


def wait_alive(session, bridge_id: str, deadline_s: float = 120.0) -> None:
    keys = wire.BridgeKeys(bridge_id)
    end = time.monotonic() + deadline_s
    while not token_up(session, keys.alive):
        if time.monotonic() > end:
            raise TimeoutError("the bridge did not come up")
        time.sleep(0.2)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    plans = [rng.uniform(-1, 1, (EPISODE_STEPS, 4)).astype(np.float32) for _ in range(args.episodes)]
    local = ValveSim(TASK, args.seed, render_quality="fast")
    local_walls: list[float] = []
    walls: list[float] = []
    env_times: list[float] = []
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = ["--bridge-id", "bench", "--task", TASK, "--seed", str(args.seed), "--connect", endpoint]
    with open_router(endpoint), open_client(endpoint) as session:
        proc = subprocess.Popen([sys.executable, "-m", "services.robot_bridge", *argv],
                                env={**followed(), "MUJOCO_GL": "egl"}, stderr=subprocess.DEVNULL)
        try:
            wait_alive(session, "bench")
            remote = BridgeEnv(session, "bench", client="bench")
            for actions in plans:
                local_walls += episode(local, actions.astype(np.float64))[0]
                w, e = episode(remote, actions)
                walls += w
                env_times += e
        finally:
            proc.terminate()
            proc.wait(timeout=60)
            local.close()
    added_ms = (np.array(walls) - np.array(env_times)) * 1000.0
    local_rate, bridge_rate = len(local_walls) / sum(local_walls), len(walls) / sum(walls)
    result = {
        "task": TASK,
        "steps": len(walls),
        "in_process_steps_per_s": round(local_rate, 1),
        "bridge_steps_per_s": round(bridge_rate, 1),
        "bridge_to_in_process": round(bridge_rate / local_rate, 3),
        "added_latency_ms_median": round(float(np.median(added_ms)), 3),
        "added_latency_ms_p90": round(float(np.percentile(added_ms, 90)), 3),
    }
    print(f"in-process {local_rate:.1f}/s  through the bridge {bridge_rate:.1f}/s "
          f"({bridge_rate / local_rate:.2f}x)  added latency median {result['added_latency_ms_median']} ms")
    print(json.dumps(result))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.robot"):
        main()
