"""SAC-AE (Yarats et al., denisyarats/pytorch_sac_ae) with its own settings.

The critic owns the encoder and has a target copy (encoder tau 0.05); the
actor's encoder shares the critic's convolutions, which only the critic loss
and the autoencoder train; the decoder target is the 5-bit observation
centred on zero, with uniform dequantisation noise.
"""

from __future__ import annotations

import copy
import math

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
from shared.nets import Decoder, Encoder, GaussianActor, TwinQ


def preprocess_obs(obs: torch.Tensor, bits: int = 5) -> torch.Tensor:
    """SAC-AE's reconstruction target: quantise to `bits`, dequantise with noise, centre on 0."""
    bins = 2**bits
    x = torch.floor(obs.float() / 2 ** (8 - bits)) / bins
    return x + torch.rand_like(x) / bins - 0.5


class SACAE(ModuleStateMixin):
    algo = "sac_ae"
    view = ("critic_encoder", "decoder")  # the decoder is trained on the critic's encoder
    uses_intrinsic = False

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        action_dim: int,
        config: AgentConfig,
        device: torch.device,
    ) -> None:
        c = config
        self.config = config
        self.device = device
        self.action_dim = action_dim
        make_encoder = lambda: Encoder(  # noqa: E731
            obs_shape,
            c.latent_dim,
            c.num_filters,
            c.num_conv_layers,
            pixel_scale=255.0,
            precision=c.pixel_precision,
        )
        self.critic_encoder = make_encoder().to(device)
        self.actor_encoder = make_encoder().to(device)
        self.actor_encoder.copy_conv_weights_from(self.critic_encoder)
        self.critic = TwinQ(c.latent_dim, action_dim, c.hidden_dim).to(device)
        self.actor = GaussianActor(c.latent_dim, action_dim, c.hidden_dim, c.log_std_min, c.log_std_max).to(
            device
        )
        self.critic_encoder_target = copy.deepcopy(self.critic_encoder)
        self.critic_target = copy.deepcopy(self.critic)
        for p in [*self.critic_encoder_target.parameters(), *self.critic_target.parameters()]:
            p.requires_grad_(False)
        self.decoder = Decoder(
            obs_shape,
            self.critic_encoder.conv_shape,
            c.latent_dim,
            c.num_filters,
            c.num_conv_layers,
            sigmoid_output=False,
            precision=c.pixel_precision,
        ).to(device)
        channels_last(self._modules().values())
        self.log_alpha = torch.tensor(math.log(c.init_temperature), device=device, requires_grad=True)
        self.target_entropy = -float(action_dim)

        # The actor's fc/LayerNorm are its own; its convolutions are the critic's and
        # get no gradient from the actor loss (detached), so listing them is harmless.
        actor_params = [*self.actor_encoder.fc.parameters(), *self.actor_encoder.ln.parameters()]
        self.actor_opt = adam(
            [*actor_params, *self.actor.parameters()], c.actor_lr, betas=(c.actor_beta, 0.999)
        )
        self.critic_opt = adam(
            [*self.critic_encoder.parameters(), *self.critic.parameters()],
            c.critic_lr,
            betas=(c.critic_beta, 0.999),
        )
        self.alpha_opt = adam([self.log_alpha], c.alpha_lr, betas=(c.alpha_beta, 0.999))
        self.encoder_opt = adam(self.critic_encoder.parameters(), c.encoder_lr)
        self.decoder_opt = adam(self.decoder.parameters(), c.decoder_lr, c.decoder_weight_decay)
        self.num_updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool, rng: np.random.Generator) -> np.ndarray:
        z = self.actor_encoder(to_obs_tensor(obs, self.device))
        action, _ = self.actor(z, sample=explore)
        return action[0].clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)

    def score(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        raise RuntimeError("sac_ae has no intrinsic rewards")

    def update_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One update in SAC-AE's order: critic, actor and alpha, targets, decoder."""
        c = self.config
        self.num_updates += 1
        batch = shifted_batch(float_pixels(batch, self.config.pixel_precision), self.config.random_shift)
        obs, next_obs, action = batch["obs"], batch["next_obs"], batch["action"]
        reward = batch["reward"].view(-1, 1)
        discount = batch["discount"].view(-1, 1)
        metrics: dict[str, torch.Tensor] = {}

        with torch.no_grad():
            next_action, next_log_pi = self.actor(self.actor_encoder(next_obs))
            target_q = torch.min(*self.critic_target(self.critic_encoder_target(next_obs), next_action))
            target_v = target_q - self.alpha * next_log_pi
            q_target = reward + c.gamma * discount * target_v
        q1, q2 = self.critic(self.critic_encoder(obs), action)
        critic_loss = F.mse_loss(q1, q_target) + F.mse_loss(q2, q_target)
        optimizer_step([self.critic_opt], critic_loss)
        metrics["critic_loss"] = critic_loss.detach()

        if self._steps_actor(self.num_updates):
            pi, log_pi = self.actor(self.actor_encoder(obs, detach_conv=True))
            self.critic.requires_grad_(False)
            with torch.no_grad():
                z_critic = self.critic_encoder(obs)
            actor_q = torch.min(*self.critic(z_critic, pi))
            self.critic.requires_grad_(True)
            actor_loss = (self.alpha.detach() * log_pi - actor_q).mean()
            optimizer_step([self.actor_opt], actor_loss)
            alpha_loss = (self.alpha * (-log_pi - self.target_entropy).detach()).mean()
            optimizer_step([self.alpha_opt], alpha_loss)
            metrics |= {"actor_loss": actor_loss.detach(), "alpha": self.alpha.detach()}
            soft_update(self.critic_target, self.critic, c.tau)
            soft_update(self.critic_encoder_target, self.critic_encoder, c.encoder_tau)

        z = self.critic_encoder(obs)
        rec_loss = F.mse_loss(self.decoder(z), preprocess_obs(obs))
        ae_loss = rec_loss + c.decoder_latent_lambda * (0.5 * z.pow(2).sum(dim=1)).mean()
        optimizer_step([self.encoder_opt, self.decoder_opt], ae_loss)
        metrics["ae_loss"] = ae_loss.detach()
        return metrics

    def _steps_actor(self, update: int) -> bool:
        """Whether update number `update` also steps the actor, alpha and the targets. SAC-AE's
        train.py decides by the env step it passes to each update, which is the update's number
        after its warm-up burst and the burst's own step for each update of the burst."""
        step = self.burst_updates if update <= self.burst_updates else update
        return step % self.config.policy_delay == 0

    def _modules(self) -> dict[str, torch.nn.Module]:
        return {
            "critic_encoder": self.critic_encoder,
            "actor_encoder": self.actor_encoder,
            "critic": self.critic,
            "actor": self.actor,
            "critic_encoder_target": self.critic_encoder_target,
            "critic_target": self.critic_target,
            "decoder": self.decoder,
        }

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {
            "actor_opt": self.actor_opt,
            "critic_opt": self.critic_opt,
            "alpha_opt": self.alpha_opt,
            "encoder_opt": self.encoder_opt,
            "decoder_opt": self.decoder_opt,
        }

    def _policy_modules(self) -> dict[str, torch.nn.Module]:
        return {"encoder": self.actor_encoder, "actor": self.actor}

    def state_dict(self) -> dict:
        return super().state_dict() | {"log_alpha": self.log_alpha.detach().clone()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
