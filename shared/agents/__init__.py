"""The agents: NaSA-TD3 and its baselines behind one constructor.

`TD3` (td3.py) is the shared core; `PixelTD3` is TD3 alone, `TD3AE` adds the
autoencoder, `NaSATD3` adds to TD3AE the intrinsic rewards; `SACAE` stands apart.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from shared.agents.base import Agent, batch_to_device, collect_action
from shared.agents.nasa_td3 import NaSATD3, UnscoredBatchError
from shared.agents.sac_ae import SACAE
from shared.agents.td3 import TD3, PixelTD3
from shared.agents.td3_ae import TD3AE
from shared.config import AgentConfig, ConfigError, TrainConfig, check_algo
from shared.schedule import burst_updates

if TYPE_CHECKING:
    from shared.envs import EnvSpec

AGENTS: dict[str, type[TD3] | type[SACAE]] = {
    "nasa_td3": NaSATD3,
    "td3_ae": TD3AE,
    "pixel_td3": PixelTD3,
    "sac_ae": SACAE,
}


def make_agent(
    algo: str,
    obs_shape: tuple[int, int, int],
    action_dim: int,
    config: AgentConfig,
    device: torch.device,
    updates: bool = True,
) -> Agent:
    """The agent of `algo`; `updates`: False where it only acts (actors, the evaluator), which then
    ignore the options of its updates (`cuda_graph` on a learner that has a GPU)."""
    check_algo(algo)
    if updates:
        check_update_device(config, device)
    return AGENTS[algo](obs_shape, action_dim, config, device)


def make_updating_agent(config: TrainConfig, spec: EnvSpec, device: torch.device) -> Agent:
    """The agent that makes a run's updates (`nasa train`'s, the learner's), with the run's warm-up
    burst (shared.schedule.burst_updates) set on it."""
    agent = make_agent(config.algo, spec.obs_shape, spec.action_dim, config.agent, device)
    agent.burst_updates = burst_updates(config)
    return agent


def check_update_device(config: AgentConfig, device: torch.device) -> None:
    """ConfigError if the agent's updates cannot run on `device`."""
    if config.cuda_graph and device.type != "cuda":
        raise ConfigError(f"agent.cuda_graph needs a CUDA device, and this run's device is {device}")


__all__ = [
    "AGENTS",
    "Agent",
    "NaSATD3",
    "PixelTD3",
    "SACAE",
    "TD3",
    "TD3AE",
    "UnscoredBatchError",
    "batch_to_device",
    "check_update_device",
    "collect_action",
    "make_agent",
    "make_updating_agent",
]
