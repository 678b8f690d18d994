"""NaSA-TD3 and its TD3 baselines on one code base.

- `nasa_td3`: TD3 + autoencoder + novelty/surprise intrinsic rewards (ensemble predictor).
- `td3_ae`: the same without intrinsic rewards (no ensemble).
- `pixel_td3`: the conv encoder trained by the critic only; no decoder.

Gradient routing follows the reference (UoA-CARES/NaSA_TD3): the critic loss
updates the whole encoder, the actor loss reaches no encoder parameter, and the
target actor and critic use the online encoder (there is no target encoder).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F

from shared import intrinsic
from shared.agents.base import (
    ModuleStateMixin,
    adam,
    channels_last,
    optimizer_step,
    soft_update,
    to_obs_tensor,
)
from shared.config import AgentConfig
from shared.nets import Decoder, DeterministicActor, Encoder, Ensemble, TwinQ


class TD3AE(ModuleStateMixin):
    def __init__(
        self,
        algo: str,
        obs_shape: tuple[int, int, int],
        action_dim: int,
        config: AgentConfig,
        device: torch.device,
    ) -> None:
        if algo not in ("nasa_td3", "td3_ae", "pixel_td3"):
            raise ValueError(f"TD3AE does not implement {algo!r}")
        self.algo = algo
        self.config = config
        self.device = device
        self.action_dim = action_dim
        self.uses_decoder = algo != "pixel_td3"
        self.uses_intrinsic = algo == "nasa_td3"
        c = config

        self.encoder = Encoder(obs_shape, c.latent_dim, c.num_filters, c.num_conv_layers).to(device)
        self.actor = DeterministicActor(c.latent_dim, action_dim, c.hidden_dim).to(device)
        self.critic = TwinQ(c.latent_dim, action_dim, c.hidden_dim).to(device)
        # Targets hold the heads only: the online encoder serves both.
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for p in [*self.actor_target.parameters(), *self.critic_target.parameters()]:
            p.requires_grad_(False)

        self.actor_opt = adam(self.actor.parameters(), c.actor_lr)
        # The critic's optimizer holds the encoder too, and so does the autoencoder's:
        # the reference does this on purpose, so the encoder takes both updates.
        self.critic_opt = adam([*self.critic.parameters(), *self.encoder.parameters()], c.critic_lr)
        if self.uses_decoder:
            self.decoder = Decoder(
                obs_shape, self.encoder.conv_shape, c.latent_dim, c.num_filters, c.num_conv_layers
            ).to(device)
            self.encoder_opt = adam(self.encoder.parameters(), c.encoder_lr)
            self.decoder_opt = adam(self.decoder.parameters(), c.decoder_lr, c.decoder_weight_decay)
        if self.uses_intrinsic:
            self.ensemble = Ensemble(c.latent_dim, action_dim, c.ensemble_hidden_dim, c.ensemble_size).to(
                device
            )
            # One Adam over all members equals one per member: each member's loss
            # reaches only its own parameters, and Adam is per parameter.
            self.ensemble_opt = adam(self.ensemble.parameters(), c.ensemble_lr, c.ensemble_weight_decay)
        channels_last(self._modules().values())
        self.num_updates = 0

    # -- acting ---------------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool, rng: np.random.Generator) -> np.ndarray:
        action = self.actor(self.encoder(to_obs_tensor(obs, self.device)))[0].cpu().numpy()
        if explore:
            action = action + rng.normal(0.0, self.config.exploration_noise, size=action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    # -- intrinsic rewards ----------------------------------------------------

    def score(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Novelty, surprise and their weighted sum (`intrinsic`) per transition."""
        return self.score_with_next_latent(obs, action, next_obs)[0]

    @torch.no_grad()
    def score_with_next_latent(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """`score` (`latent`: Enc(obs) already computed with the current weights), and
        Enc(next_obs), which a fresh-timing update's TD target reuses."""
        if not self.uses_intrinsic:
            raise RuntimeError(f"{self.algo} has no intrinsic rewards")
        z = self.encoder(obs) if latent is None else latent
        z_next = self.encode_next(obs, z, next_obs)
        novelty = intrinsic.novelty(obs, self.decoder(z))
        surprise = intrinsic.surprise(self.ensemble(z, action), z_next)
        total = self.config.novelty_weight * novelty + self.config.surprise_weight * surprise
        return {"novelty": novelty, "surprise": surprise, "intrinsic": total}, z_next

    @torch.no_grad()
    def encode_next(self, obs: torch.Tensor, z: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Enc(next_obs), taken from z = Enc(obs) for rows whose next stack is another row's stack.

        Transitions scored in the order they were stored chain that way (row i's
        next_obs is its successor's obs), which spares about half the encoder passes;
        an i.i.d. batch finds no chain and only pays the lookup."""
        source = chained_rows(obs, next_obs)
        unchained = source < 0
        z_next = z[source.clamp(min=0)]
        if unchained.any():
            z_next[unchained] = self.encoder(next_obs[unchained])
        return z_next

    # -- learning -------------------------------------------------------------

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One update in the reference's order: critic, autoencoder, actor (delayed), ensemble."""
        c = self.config
        self.num_updates += 1
        obs, next_obs, action = batch["obs"], batch["next_obs"], batch["action"]
        reward = batch["reward"].view(-1, 1)
        metrics: dict[str, float] = {}
        latent = next_latent = None
        if self.uses_intrinsic:
            if c.intrinsic_timing == "fresh":
                # Scoring, the TD target and the critic's forward pass all read the current
                # weights: one Enc(obs) (kept with its graph for the critic's loss) and one
                # Enc(next_obs) serve all three.
                latent = self.encoder(obs)
                scores, next_latent = self.score_with_next_latent(obs, action, next_obs, latent.detach())
                bonus = scores["intrinsic"]
            else:
                bonus = torch.nan_to_num(batch["intrinsic"], nan=0.0)
            reward = reward + bonus.view(-1, 1)
            metrics["intrinsic_batch_mean"] = bonus.mean().item()
        q_target = self.td_target(reward, batch["discount"].view(-1, 1), next_obs, next_latent)
        if self.uses_decoder and c.shared_encoder_pass:
            metrics |= self.update_critic_and_autoencoder(obs, action, q_target, latent)
        else:
            metrics |= self.update_critic(obs, action, q_target, latent)
            if self.uses_decoder:
                metrics |= self.update_autoencoder(obs)
        z_now = None
        if self.num_updates % c.policy_delay == 0:
            with torch.no_grad():
                z_now = self.encoder(obs)
            metrics |= self.update_actor(z_now)
            soft_update(self.critic_target, self.critic, c.tau)
            soft_update(self.actor_target, self.actor, c.tau)
        if self.uses_intrinsic and self.num_updates % c.ensemble_every == 0:
            metrics |= self.update_ensemble(obs, action, next_obs, z_now)
        return metrics

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
    ) -> dict[str, float]:
        """The critic loss trains the Q heads and the whole encoder (conv, fc, LayerNorm);
        `latent`: Enc(obs) with its graph, already computed with the current weights."""
        z = self.encoder(obs) if latent is None else latent
        loss = self.critic_loss(z, action, q_target)
        optimizer_step([self.critic_opt], loss)
        return {"critic_loss": loss.item()}

    def update_autoencoder(self, obs: torch.Tensor) -> dict[str, float]:
        """Reconstruction + latent penalty; the reference encodes again after the critic step."""
        loss = self._ae_loss(obs, self.encoder(obs))
        optimizer_step([self.encoder_opt, self.decoder_opt], loss)
        return {"ae_loss": loss.item()}

    def update_critic_and_autoencoder(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        q_target: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> dict[str, float]:
        """`shared_encoder_pass`: one encoder pass and one backward for both losses (not the reference)."""
        z = self.encoder(obs) if latent is None else latent
        critic_loss = self.critic_loss(z, action, q_target)
        ae_loss = self._ae_loss(obs, z)
        optimizer_step([self.critic_opt, self.encoder_opt, self.decoder_opt], critic_loss + ae_loss)
        return {"critic_loss": critic_loss.item(), "ae_loss": ae_loss.item()}

    def update_actor(self, z: torch.Tensor) -> dict[str, float]:
        """The actor loss on detached latents: it reaches no encoder parameter."""
        z = z.detach()
        self.critic.requires_grad_(False)  # the actor loss trains the actor only; skip critic grads
        loss = -torch.min(*self.critic(z, self.actor(z))).mean()
        optimizer_step([self.actor_opt], loss)
        self.critic.requires_grad_(True)
        return {"actor_loss": loss.item()}

    def update_ensemble(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, z: torch.Tensor | None = None
    ) -> dict[str, float]:
        """Each predictor regresses Enc(next_obs) from (Enc(obs), action), on detached latents."""
        with torch.no_grad():
            z = self.encoder(obs) if z is None else z
            z_next = self.encoder(next_obs)
        predictions = self.ensemble(z, action)
        # Sum of the members' MSEs: each member gets exactly its own gradient.
        loss = (predictions - z_next).pow(2).mean(dim=(1, 2)).sum()
        optimizer_step([self.ensemble_opt], loss)
        return {"ensemble_loss": loss.item() / self.config.ensemble_size}

    def _ae_loss(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        reconstruction = self.decoder(z)
        rec_loss = F.mse_loss(reconstruction, obs.float() / 255.0)
        latent_loss = (0.5 * z.pow(2).sum(dim=1)).mean()
        return rec_loss + self.config.decoder_latent_lambda * latent_loss

    # -- state ----------------------------------------------------------------

    def _modules(self) -> dict[str, torch.nn.Module]:
        modules = {
            "encoder": self.encoder,
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
        }
        if self.uses_decoder:
            modules["decoder"] = self.decoder
        if self.uses_intrinsic:
            modules["ensemble"] = self.ensemble
        return modules

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opts = {"actor_opt": self.actor_opt, "critic_opt": self.critic_opt}
        if self.uses_decoder:
            opts |= {"encoder_opt": self.encoder_opt, "decoder_opt": self.decoder_opt}
        if self.uses_intrinsic:
            opts["ensemble_opt"] = self.ensemble_opt
        return opts

    def _policy_modules(self) -> dict[str, torch.nn.Module]:
        return {"encoder": self.encoder, "actor": self.actor}


def chained_rows(obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """For each row i, a row j with obs[j] equal to next_obs[i] (exactly), else -1.

    Candidates share a fingerprint (every 12th image row of every channel); each is
    then compared whole, so a shared fingerprint never pairs two different stacks.
    At most a few candidates are compared per row, which bounds the cost when many
    stacks share a fingerprint (a still scene): a missed pair only costs an encoder pass."""

    def fingerprints(stacks: torch.Tensor) -> list[bytes]:
        return [row.tobytes() for row in stacks[:, :, ::12].cpu().numpy()]

    candidates: dict[bytes, list[int]] = {}
    for j, key in enumerate(fingerprints(obs)):
        candidates.setdefault(key, []).append(j)
    source = [-1] * len(next_obs)
    for i, key in enumerate(fingerprints(next_obs)):
        for j in candidates.get(key, [])[:4]:
            if torch.equal(next_obs[i], obs[j]):
                source[i] = j
                break
    return torch.tensor(source, dtype=torch.long, device=obs.device)
