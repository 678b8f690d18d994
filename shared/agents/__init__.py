"""The agents: NaSA-TD3 and its baselines behind one constructor."""

from __future__ import annotations

import torch

from shared.agents.base import Agent, batch_to_device, collect_action
from shared.agents.sac_ae import SACAE
from shared.agents.td3_ae import TD3AE
from shared.config import AgentConfig, check_algo


def make_agent(
    algo: str,
    obs_shape: tuple[int, int, int],
    action_dim: int,
    config: AgentConfig,
    device: torch.device,
) -> Agent:
    check_algo(algo)
    if algo == "sac_ae":
        return SACAE(obs_shape, action_dim, config, device)
    return TD3AE(algo, obs_shape, action_dim, config, device)


__all__ = ["Agent", "batch_to_device", "collect_action", "make_agent"]
