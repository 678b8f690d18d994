"""`nasa_td3`: TD3-AE plus the novelty and surprise intrinsic rewards.

novelty = 1 - SSIM(obs, Dec(Enc(obs))) and surprise = the error of an ensemble
of latent-dynamics predictors on Enc(next_obs) (`shared.intrinsic`). The
ensemble trains after the actor, on the same batch, on detached latents.

Two timings of the bonus (`intrinsic_timing`): `collect` (the paper) reads the
score stored with each transition, which the runners' scorer fills before the
update; `fresh` rescores the batch with the current networks at each update.
"""

from __future__ import annotations

import math

import torch

from shared import intrinsic
from shared.agents.base import adam, channels_last, optimizer_step
from shared.agents.td3_ae import TD3AE
from shared.config import AgentConfig
from shared.nets import Ensemble


class UnscoredBatchError(ValueError):
    """A collect-timing update got rows with no stored intrinsic score (NaN)."""


class NaSATD3(TD3AE):
    algo = "nasa_td3"
    uses_intrinsic = True

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        action_dim: int,
        config: AgentConfig,
        device: torch.device,
    ) -> None:
        super().__init__(obs_shape, action_dim, config, device)
        c = config
        self.ensemble = Ensemble(c.latent_dim, action_dim, c.ensemble_hidden_dim, c.ensemble_size).to(device)
        # One Adam over all members equals one per member: each member's loss
        # reaches only its own parameters, and Adam is per parameter.
        self.ensemble_opt = adam(self.ensemble.parameters(), c.ensemble_lr, c.ensemble_weight_decay)
        channels_last([self.ensemble])

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
        chain: bool = True,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """`score` (`latent`: Enc(obs) already computed with the current weights), and
        Enc(next_obs), which a fresh-timing update's TD target reuses. `chain`: reuse a row's
        latent for the next stack that equals its obs (`intrinsic.encode_with_next`); the lookup reads
        the frames on the host, so a captured update encodes every next stack instead."""
        if chain:
            z, z_next = intrinsic.encode_with_next(self.encoder, obs, next_obs, latent)
        else:
            z = self.encoder(obs) if latent is None else latent
            z_next = self.encoder(next_obs)
        novelty = intrinsic.novelty_of_logits(obs, self.decoder.logits(z, keep_precision=True))
        surprise = intrinsic.surprise(self.ensemble(z, action), z_next)
        total = self.config.novelty_weight * novelty + self.config.surprise_weight * surprise
        return {"novelty": novelty, "surprise": surprise, "intrinsic": total}, z_next

    # -- learning -------------------------------------------------------------

    def update_period(self) -> int:
        return math.lcm(self.config.policy_delay, self.config.ensemble_every)

    def check_batch(self, batch: dict[str, torch.Tensor]) -> None:
        if self.config.intrinsic_timing == "collect":
            check_scored(batch["intrinsic"])

    def reward(
        self, batch: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, dict[str, torch.Tensor]]:
        """The environment's reward plus the intrinsic bonus: the stored score (`collect`),
        or the batch scored now (`fresh`)."""
        latent = next_latent = None
        if self.config.intrinsic_timing == "fresh":
            # Scoring, the TD target and the critic's forward pass all read the current
            # weights: one Enc(obs) (kept with its graph for the critic's loss) and one
            # Enc(next_obs) serve all three.
            latent = self.encoder(batch["obs"])
            scores, next_latent = self.score_with_next_latent(
                batch["obs"], batch["action"], batch["next_obs"], latent.detach(),
                chain=not self.config.cuda_graph,
            )
            bonus = scores["intrinsic"]
        else:
            bonus = batch["intrinsic"]  # checked by `check_batch`
        reward = batch["reward"].view(-1, 1) + bonus.view(-1, 1)
        return reward, latent, next_latent, {"intrinsic_batch_mean": bonus.detach().mean()}

    def update_auxiliary(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, z: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """The ensemble, on every `ensemble_every`-th update."""
        if self.num_updates % self.config.ensemble_every != 0:
            return {}
        return self.update_ensemble(obs, action, next_obs, z)

    def update_ensemble(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, z: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """Each predictor regresses Enc(next_obs) from (Enc(obs), action), on detached latents."""
        with torch.no_grad():
            z = self.encoder(obs) if z is None else z
            z_next = self.encoder(next_obs)
        predictions = self.ensemble(z, action)
        # Sum of the members' MSEs: each member gets exactly its own gradient.
        loss = (predictions - z_next).pow(2).mean(dim=(1, 2)).sum()
        optimizer_step([self.ensemble_opt], loss)
        return {"ensemble_loss": loss.detach() / self.config.ensemble_size}

    # -- state ----------------------------------------------------------------

    def _modules(self) -> dict[str, torch.nn.Module]:
        return super()._modules() | {"ensemble": self.ensemble}

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return super()._optimizers() | {"ensemble_opt": self.ensemble_opt}


def check_scored(intrinsic_reward: torch.Tensor) -> None:
    """Raise UnscoredBatchError if any row's stored intrinsic score is NaN (never scored).

    The runners score every row before a collect-timing update uses it; a NaN here
    is a scoring bug, which a zero bonus would hide."""
    unscored = torch.isnan(intrinsic_reward)
    if unscored.any():
        raise UnscoredBatchError(
            f"{int(unscored.sum())} of {unscored.numel()} rows of the batch have no intrinsic score (NaN): "
            "with intrinsic_timing 'collect' every row must be scored before the update uses it"
        )
