"""`td3_ae`: TD3 with a conv autoencoder on its encoder (no intrinsic rewards).

The encoder takes two updates per batch, as in the reference: the critic's
(its optimizer holds the encoder) and the autoencoder's (reconstruction of the
observation plus a latent penalty, after the critic step, on a fresh encoding).
"""

from __future__ import annotations

import torch

from shared.agents.base import adam, channels_last, optimizer_step
from shared.agents.td3 import TD3
from shared.config import AgentConfig
from shared.nets import Decoder, sigmoid_mse


class TD3AE(TD3):
    algo = "td3_ae"
    view = ("encoder", "decoder")

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        action_dim: int,
        config: AgentConfig,
        device: torch.device,
    ) -> None:
        super().__init__(obs_shape, action_dim, config, device)
        c = config
        self.decoder = Decoder(
            obs_shape,
            self.encoder.conv_shape,
            c.latent_dim,
            c.num_filters,
            c.num_conv_layers,
            precision=c.pixel_precision,
        ).to(device)
        # The encoder's second optimizer, beside the critic's: the reference's choice.
        self.encoder_opt = adam(self.encoder.parameters(), c.encoder_lr)
        self.decoder_opt = adam(self.decoder.parameters(), c.decoder_lr, c.decoder_weight_decay)
        channels_last([self.decoder])

    def update_encoder(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        q_target: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The critic's step then the autoencoder's, or both in one (`shared_encoder_pass`)."""
        if self.config.shared_encoder_pass:
            return self.update_critic_and_autoencoder(obs, action, q_target, latent)
        metrics = self.update_critic(obs, action, q_target, latent)
        return metrics | self.update_autoencoder(obs)

    def update_autoencoder(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Reconstruction + latent penalty; the reference encodes again after the critic step."""
        loss = self._ae_loss(obs, self.encoder(obs))
        optimizer_step([self.encoder_opt, self.decoder_opt], loss)
        return {"ae_loss": loss.detach()}

    def update_critic_and_autoencoder(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        q_target: torch.Tensor,
        latent: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """`shared_encoder_pass`: one encoder pass and one backward for both losses (not the reference)."""
        z = self.encoder(obs) if latent is None else latent
        critic_loss = self.critic_loss(z, action, q_target)
        ae_loss = self._ae_loss(obs, z)
        optimizer_step([self.critic_opt, self.encoder_opt, self.decoder_opt], critic_loss + ae_loss)
        return {"critic_loss": critic_loss.detach(), "ae_loss": ae_loss.detach()}

    def _ae_loss(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        rec_loss = sigmoid_mse(self.decoder.logits(z), obs)
        latent_loss = (0.5 * z.pow(2).sum(dim=1)).mean()
        return rec_loss + self.config.decoder_latent_lambda * latent_loss

    def _modules(self) -> dict[str, torch.nn.Module]:
        return super()._modules() | {"decoder": self.decoder}

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return super()._optimizers() | {"encoder_opt": self.encoder_opt, "decoder_opt": self.decoder_opt}
