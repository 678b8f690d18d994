"""TD3 on pixels: the base of NaSA-TD3 and its baselines, and `pixel_td3` itself.

`TD3` holds what every TD3 variant here shares: the conv encoder, the
deterministic actor, the twin critic, their target heads, the TD target, the
critic and actor updates, acting, and the state. `PixelTD3` is that and nothing
more: the encoder is trained by the critic only.

Gradient routing follows the reference (UoA-CARES/NaSA_TD3): the critic loss
updates the whole encoder, the actor loss reaches no encoder parameter, and the
target actor and critic use the online encoder (there is no target encoder).

One update runs in the reference's order through three steps a variant may
extend: the reward (`reward`), every loss that trains the encoder
(`update_encoder`), then, after the delayed actor step, the models trained on
the same batch (`update_auxiliary`).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F

from shared.agents.base import (
    ModuleStateMixin,
    adam,
    channels_last,
    float_pixels,
    optimizer_step,
    soft_update,
    to_obs_tensor,
)
from shared.augment import shifted_batch
from shared.config import AgentConfig
from shared.nets import DeterministicActor, Encoder, TwinQ


class TD3(ModuleStateMixin):
    """The shared TD3 core on a conv encoder; subclasses name their `algo`."""

    algo: str
    uses_intrinsic = False

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        action_dim: int,
        config: AgentConfig,
        device: torch.device,
    ) -> None:
        self.config = config
        self.device = device
        self.obs_shape = obs_shape
        self.action_dim = action_dim
        c = config
        self.encoder = Encoder(
            obs_shape, c.latent_dim, c.num_filters, c.num_conv_layers, precision=c.pixel_precision
        ).to(device)
        self.actor = DeterministicActor(c.latent_dim, action_dim, c.hidden_dim).to(device)
        self.critic = TwinQ(c.latent_dim, action_dim, c.hidden_dim).to(device)
        # Targets hold the heads only: the online encoder serves both.
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for p in [*self.actor_target.parameters(), *self.critic_target.parameters()]:
            p.requires_grad_(False)
        self.actor_opt = adam(self.actor.parameters(), c.actor_lr)
        # The critic's optimizer holds the encoder: the critic loss trains the whole encoder
        # (TD3AE's autoencoder optimizer holds it too, as the reference does on purpose).
        self.critic_opt = adam([*self.critic.parameters(), *self.encoder.parameters()], c.critic_lr)
        channels_last([self.encoder, self.actor, self.critic, self.actor_target, self.critic_target])
        self.num_updates = 0

    # -- acting ---------------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool, rng: np.random.Generator) -> np.ndarray:
        action = self.actor(self.encoder(to_obs_tensor(obs, self.device)))[0].cpu().numpy()
        if explore:
            action = action + rng.normal(0.0, self.config.exploration_noise, size=action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def score(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        raise RuntimeError(f"{self.algo} has no intrinsic rewards")

    # -- learning -------------------------------------------------------------

    def update_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One update: reward, encoder losses (critic first), delayed actor and targets, auxiliaries."""
        c = self.config
        batch = shifted_batch(float_pixels(batch, self.config.pixel_precision), self.config.random_shift)
        obs, next_obs, action = batch["obs"], batch["next_obs"], batch["action"]
        reward, latent, next_latent, metrics = self.reward(batch)  # first: it may refuse the batch
        self.num_updates += 1
        q_target = self.td_target(reward, batch["discount"].view(-1, 1), next_obs, next_latent)
        metrics |= self.update_encoder(obs, action, q_target, latent)
        z_now = None
        if self.num_updates % c.policy_delay == 0:
            with torch.no_grad():
                z_now = self.encoder(obs)
            metrics |= self.update_actor(z_now)
            soft_update(self.critic_target, self.critic, c.tau)
            soft_update(self.actor_target, self.actor, c.tau)
        metrics |= self.update_auxiliary(obs, action, next_obs, z_now)
        return metrics

    def reward(
        self, batch: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, dict[str, torch.Tensor]]:
        """The (B, 1) reward the TD target uses, with Enc(obs) (its graph kept) and Enc(next_obs)
        when computing the reward already encoded them with the current weights (else None),
        and the reward's metrics. Here: the environment's reward alone."""
        return batch["reward"].view(-1, 1), None, None, {}

    def update_encoder(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        q_target: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """Every loss that trains the encoder: here the critic's alone."""
        return self.update_critic(obs, action, q_target, latent)

    def update_auxiliary(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, z: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """Models trained after the actor on the same batch (`z`: Enc(obs) of this update's actor
        step, or None); none here."""
        return {}

    @torch.no_grad()
    def td_target(
        self,
        reward: torch.Tensor,
        discount: torch.Tensor,
        next_obs: torch.Tensor,
        next_latent: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Clipped double-Q target with target policy smoothing; targets read the online encoder
        (`next_latent`: Enc(next_obs) already computed with the current weights)."""
        c = self.config
        z_next = self.encoder(next_obs) if next_latent is None else next_latent
        next_action = self.actor_target(z_next)
        noise = (torch.randn_like(next_action) * c.target_noise).clamp(
            -c.target_noise_clip, c.target_noise_clip
        )
        next_action = (next_action + noise).clamp(-1.0, 1.0)
        return reward + c.gamma * discount * torch.min(*self.critic_target(z_next, next_action))

    def critic_loss(self, z: torch.Tensor, action: torch.Tensor, q_target: torch.Tensor) -> torch.Tensor:
        q1, q2 = self.critic(z, action)
        return F.mse_loss(q1, q_target) + F.mse_loss(q2, q_target)

    def update_critic(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        q_target: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The critic loss trains the Q heads and the whole encoder (conv, fc, LayerNorm);
        `latent`: Enc(obs) with its graph, already computed with the current weights."""
        z = self.encoder(obs) if latent is None else latent
        loss = self.critic_loss(z, action, q_target)
        optimizer_step([self.critic_opt], loss)
        return {"critic_loss": loss.detach()}

    def update_actor(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        """The actor loss on detached latents: it reaches no encoder parameter."""
        z = z.detach()
        self.critic.requires_grad_(False)  # the actor loss trains the actor only; skip critic grads
        loss = -torch.min(*self.critic(z, self.actor(z))).mean()
        optimizer_step([self.actor_opt], loss)
        self.critic.requires_grad_(True)
        return {"actor_loss": loss.detach()}

    # -- state ----------------------------------------------------------------

    def _modules(self) -> dict[str, torch.nn.Module]:
        return {
            "encoder": self.encoder,
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
        }

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"actor_opt": self.actor_opt, "critic_opt": self.critic_opt}

    def _policy_modules(self) -> dict[str, torch.nn.Module]:
        return {"encoder": self.encoder, "actor": self.actor}


class PixelTD3(TD3):
    """`pixel_td3`: TD3 whose conv encoder is trained by the critic only; no decoder."""

    algo = "pixel_td3"
