"""The baselines' updates against their reference code's formulas, written out here.

SAC-AE is checked against `denisyarats/pytorch_sac_ae` (`sac_ae.py`, `utils.py`), TD3-AE against
`UoA-CARES/NaSA_TD3` (`nasa_td3.py` with the intrinsic rewards off). Each test starts a plain-torch
re-implementation of the reference's update from the project agent's own weights, feeds both the
same batch and the same random draws, and compares every parameter after each update. The
networks' forward passes are the project's (tests/test_agents.py compares them with the
reference's); what is checked here is each update: its losses, which optimizer holds which
parameters, its order, its schedule and its targets.
"""

import copy
import math

import numpy as np
import torch
import torch.nn.functional as F

from shared.config import agent_defaults
from shared.nets import float_channels_last
from tests import test_agents as agents_test

OBS_SHAPE = (9, 48, 48)
ACTION_DIM = 2
SMALL = {"latent_dim": 16, "hidden_dim": 32, "num_filters": 8}


def make(algo: str, **overrides):
    torch.manual_seed(0)
    return agents_test.make(algo, **{**SMALL, **overrides})


def batch(seed: int, size: int = 8) -> dict[str, torch.Tensor]:
    """test_agents' batch, with some transitions terminal (discount 0) and no intrinsic reward."""
    b = agents_test.random_batch(size, seed)
    g = torch.Generator().manual_seed(seed + 1)
    return b | {"discount": (torch.rand(size, generator=g) > 0.2).float(), "intrinsic": torch.zeros(size)}


def assert_same_modules(agent, ref, names: list[str], step: int) -> None:
    for name in names:
        mine, theirs = getattr(agent, name).state_dict(), getattr(ref, name).state_dict()
        for key, value in theirs.items():
            torch.testing.assert_close(mine[key], value, rtol=1e-4, atol=1e-6,
                                       msg=f"{name}.{key} after update {step}")


# -- SAC-AE ---------------------------------------------------------------------------------


def sac_preprocess_obs(obs: torch.Tensor, bits: int = 5) -> torch.Tensor:
    """utils.preprocess_obs of the reference."""
    bins = 2**bits
    obs = torch.floor(obs / 2 ** (8 - bits)) / bins
    return obs + torch.rand_like(obs) / bins - 0.5


def sac_actor(ref, obs: torch.Tensor, detach_encoder: bool = False):
    """The reference's Actor.forward: log-std squashed by tanh into its bounds, the Gaussian's
    log-density of the sampled noise, then tanh's correction (`gaussian_logprob`, `squash`)."""
    c = ref.config
    mu, log_std = ref.actor.net(ref.actor_encoder(obs, detach_conv=detach_encoder)).chunk(2, dim=-1)
    log_std = torch.tanh(log_std)
    log_std = c.log_std_min + 0.5 * (c.log_std_max - c.log_std_min) * (log_std + 1)
    noise = torch.randn_like(mu)
    pi = mu + noise * log_std.exp()
    log_pi = (-0.5 * noise.pow(2) - log_std).sum(-1, keepdim=True) - 0.5 * np.log(2 * np.pi) * noise.size(-1)
    pi = torch.tanh(pi)
    log_pi = log_pi - torch.log(F.relu(1 - pi.pow(2)) + 1e-6).sum(-1, keepdim=True)
    return pi, log_pi


class SacAeReference:
    """SacAeAgent's update, at train.py's settings, on copies of a project agent's networks."""

    def __init__(self, agent) -> None:
        c = self.config = agent.config
        # One deepcopy keeps the actor's convolutions tied to the critic's, as the reference ties them.
        nets = copy.deepcopy({n: getattr(agent, n) for n in (
            "critic_encoder", "actor_encoder", "critic", "actor", "critic_encoder_target", "critic_target",
            "decoder")})
        for name, net in nets.items():
            setattr(self, name, net)
        assert self.actor_encoder.convs[0].weight is self.critic_encoder.convs[0].weight
        self.log_alpha = torch.tensor(math.log(0.1), requires_grad=True)
        self.target_entropy = -ACTION_DIM
        # The reference's optimizers: the actor's holds its whole encoder (the tied convolutions
        # too), the critic's the critic's encoder, the autoencoder's the critic's encoder again.
        self.actor_opt = torch.optim.Adam([*self.actor_encoder.parameters(), *self.actor.parameters()],
                                          lr=1e-3, betas=(0.9, 0.999))
        self.critic_opt = torch.optim.Adam([*self.critic_encoder.parameters(), *self.critic.parameters()],
                                           lr=1e-3, betas=(0.9, 0.999))
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=1e-4, betas=(0.5, 0.999))
        self.encoder_opt = torch.optim.Adam(self.critic_encoder.parameters(), lr=1e-3)
        self.decoder_opt = torch.optim.Adam(self.decoder.parameters(), lr=1e-3, weight_decay=1e-7)
        assert (c.tau, c.encoder_tau, c.decoder_latent_lambda) == (0.01, 0.05, 1e-6)

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def critic_q(self, obs, action, encoder, critic, detach_encoder=False):
        return critic(encoder(obs, detach_conv=detach_encoder), action)

    def update(self, b: dict[str, torch.Tensor], step: int) -> None:
        obs = float_channels_last(b["obs"])  # the rand_like of preprocess_obs draws in this layout
        next_obs = float_channels_last(b["next_obs"])
        action, reward, not_done = b["action"], b["reward"].view(-1, 1), b["discount"].view(-1, 1)
        with torch.no_grad():
            policy_action, log_pi = sac_actor(self, next_obs)
            target_q = torch.min(*self.critic_q(next_obs, policy_action, self.critic_encoder_target,
                                                self.critic_target))
            target_v = target_q - self.alpha.detach() * log_pi
            target = reward + not_done * 0.99 * target_v
        q1, q2 = self.critic_q(obs, action, self.critic_encoder, self.critic)
        critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()

        if step % 2 == 0:  # actor_update_freq
            pi, log_pi = sac_actor(self, obs, detach_encoder=True)
            actor_q = torch.min(*self.critic_q(obs, pi, self.critic_encoder, self.critic,
                                               detach_encoder=True))
            actor_loss = (self.alpha.detach() * log_pi - actor_q).mean()
            self.actor_opt.zero_grad()
            actor_loss.backward()
            self.actor_opt.step()
            self.alpha_opt.zero_grad()
            alpha_loss = (self.alpha * (-log_pi - self.target_entropy).detach()).mean()
            alpha_loss.backward()
            self.alpha_opt.step()
        if step % 2 == 0:  # critic_target_update_freq
            soft(self.critic, self.critic_target, 0.01)
            soft(self.critic_encoder, self.critic_encoder_target, 0.05)

        h = self.critic_encoder(obs)
        rec_loss = F.mse_loss(sac_preprocess_obs(obs), self.decoder(h))
        loss = rec_loss + 1e-6 * (0.5 * h.pow(2).sum(1)).mean()
        self.encoder_opt.zero_grad()
        self.decoder_opt.zero_grad()
        loss.backward()
        self.encoder_opt.step()
        self.decoder_opt.step()


def soft(net: torch.nn.Module, target: torch.nn.Module, tau: float) -> None:
    """utils.soft_update_params of the reference."""
    for param, target_param in zip(net.parameters(), target.parameters(), strict=True):
        target_param.data.copy_(tau * param.data + (1 - tau) * target_param.data)


SAC_MODULES = ["critic_encoder", "actor_encoder", "critic", "actor", "critic_encoder_target",
               "critic_target", "decoder"]


def test_sac_ae_updates_are_the_references():
    agent = make("sac_ae")
    ref = SacAeReference(agent)
    for step in range(1, 7):  # odd updates: critic and decoder; even: actor, alpha and targets too
        b = batch(step)
        torch.manual_seed(100 + step)
        agent.update(b)
        torch.manual_seed(100 + step)
        ref.update(b, step)
        assert_same_modules(agent, ref, SAC_MODULES, step)
        torch.testing.assert_close(agent.log_alpha, ref.log_alpha.detach(), rtol=0, atol=1e-6)


def test_sac_ae_warm_up_bursts_updates_step_the_actor_as_the_bursts_env_step_says():
    """train.py passes its env step to each update: every update of the burst gets the burst's step,
    so they all step the actor, alpha and the targets (an even warm-up) or none do (an odd one)."""
    for burst in (4, 3):
        agent = make("sac_ae")
        agent.burst_updates = burst
        ref = SacAeReference(agent)
        for update in range(1, burst + 4):
            b = batch(update)
            torch.manual_seed(100 + update)
            agent.update(b)
            torch.manual_seed(100 + update)
            ref.update(b, burst if update <= burst else update)
            assert_same_modules(agent, ref, SAC_MODULES, update)
            torch.testing.assert_close(agent.log_alpha, ref.log_alpha.detach(), rtol=0, atol=1e-6)


def test_sac_ae_defaults_are_train_pys():
    """train.py's argument defaults, which the reference's published runs use."""
    c = agent_defaults("sac_ae")
    assert (c.latent_dim, c.hidden_dim, c.num_filters, c.num_conv_layers) == (50, 1024, 32, 4)
    assert (c.actor_lr, c.critic_lr, c.encoder_lr, c.decoder_lr, c.alpha_lr) == (1e-3, 1e-3, 1e-3, 1e-3, 1e-4)
    assert (c.actor_beta, c.critic_beta, c.alpha_beta) == (0.9, 0.9, 0.5)
    assert (c.tau, c.encoder_tau, c.policy_delay, c.gamma) == (0.01, 0.05, 2, 0.99)
    assert (c.init_temperature, c.log_std_min, c.log_std_max) == (0.1, -10.0, 2.0)
    assert (c.decoder_latent_lambda, c.decoder_weight_decay) == (1e-6, 1e-7)


# -- TD3-AE ---------------------------------------------------------------------------------


class Td3AeReference:
    """AE_TD3.train_policy of the NaSA-TD3 reference (no intrinsic reward, so no ensemble), on
    copies of a project agent's networks. Its actor and critic hold the one online encoder, and
    so do their targets: the project's target heads read the online encoder the same way."""

    def __init__(self, agent) -> None:
        nets = copy.deepcopy({n: getattr(agent, n) for n in (
            "encoder", "decoder", "actor", "critic", "actor_target", "critic_target")})
        for name, net in nets.items():
            setattr(self, name, net)
        enc = list(self.encoder.parameters())
        # Adam over actor.parameters() and critic.parameters() of the reference: each holds the encoder.
        self.actor_opt = torch.optim.Adam([*self.actor.parameters(), *enc], lr=1e-4)
        self.critic_opt = torch.optim.Adam([*self.critic.parameters(), *enc], lr=1e-3)
        self.encoder_opt = torch.optim.Adam(enc, lr=1e-4)
        self.decoder_opt = torch.optim.Adam(self.decoder.parameters(), lr=1e-4, weight_decay=1e-7)
        self.learn_counter = 0

    def update(self, b: dict[str, torch.Tensor]) -> None:
        self.learn_counter += 1
        states, next_states = b["obs"].float(), b["next_obs"].float()
        actions, rewards, not_done = b["action"], b["reward"].view(-1, 1), b["discount"].view(-1, 1)
        with torch.no_grad():
            next_actions = self.actor_target(self.encoder(next_states))
            target_noise = torch.clamp(0.2 * torch.randn_like(next_actions), -0.5, 0.5)
            next_actions = torch.clamp(next_actions + target_noise, min=-1, max=1)
            target_q = torch.minimum(*self.critic_target(self.encoder(next_states), next_actions))
            q_target = rewards + 0.99 * not_done * target_q
        q1, q2 = self.critic(self.encoder(states), actions)
        critic_loss = F.mse_loss(q1, q_target) + F.mse_loss(q2, q_target)
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()

        z = self.encoder(states)
        rec_loss = F.mse_loss(states / 255, self.decoder(z))
        ae_loss = rec_loss + 1e-6 * (0.5 * z.pow(2).sum(1)).mean()
        self.encoder_opt.zero_grad()
        self.decoder_opt.zero_grad()
        ae_loss.backward()
        self.encoder_opt.step()
        self.decoder_opt.step()

        if self.learn_counter % 2 == 0:
            z = self.encoder(states).detach()  # detach_encoder=True: after the tanh
            actor_loss = -torch.minimum(*self.critic(z, self.actor(z))).mean()
            self.actor_opt.zero_grad()
            actor_loss.backward()
            self.actor_opt.step()
            soft(self.critic, self.critic_target, 0.005)
            soft(self.actor, self.actor_target, 0.005)


def test_td3_ae_updates_are_the_references():
    agent = make("td3_ae")
    ref = Td3AeReference(agent)
    for step in range(1, 5):
        b = batch(step)
        torch.manual_seed(100 + step)
        agent.update(b)
        torch.manual_seed(100 + step)
        ref.update(b)
        assert_same_modules(agent, ref, ["encoder", "decoder", "actor", "critic", "actor_target",
                                         "critic_target"], step)


def test_sac_ae_encoder_and_decoder_are_the_references_pixel_networks():
    """PixelEncoder: obs / 255, convolutions with ReLU, (c, h, w) flatten, fc, LayerNorm, tanh;
    PixelDecoder: fc, ReLU, transposed convolutions, no squashing at the end. The project's fc
    layers read the conv features in (h, w, c) order (tests/test_agents.py), relabelled here."""
    agent = make("sac_ae")
    encoder, decoder = agent.critic_encoder, agent.decoder
    c, h, w = encoder.conv_shape
    ref_of_ours = torch.argsort(torch.arange(c * h * w).view(c, h, w).permute(1, 2, 0).flatten())
    obs = batch(0)["obs"]
    with torch.no_grad():
        x = obs.float() / 255.0
        for conv in [m for m in encoder.convs if isinstance(m, torch.nn.Conv2d)]:
            x = torch.relu(conv(x))
        fc = F.linear(x.flatten(1), encoder.fc.weight[:, ref_of_ours], encoder.fc.bias)
        z = torch.tanh(encoder.ln(fc))
        torch.testing.assert_close(encoder(obs), z, rtol=1e-5, atol=1e-5)

        y = torch.relu(F.linear(z, decoder.fc.weight[ref_of_ours], decoder.fc.bias[ref_of_ours]))
        y = y.view(-1, c, h, w)
        deconvs = [m for m in decoder.deconvs if isinstance(m, torch.nn.ConvTranspose2d)]
        for deconv in deconvs[:-1]:
            y = torch.relu(deconv(y))
        torch.testing.assert_close(decoder(z), deconvs[-1](y), rtol=1e-5, atol=1e-5)
