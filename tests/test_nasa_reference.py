"""NaSA-TD3 against the reference's own code (UoA-CARES/NaSA_TD3), imported from a checkout.

tests/test_baselines_reference.py writes TD3-AE's reference update out by hand. Here the
reference's `AE_TD3` itself runs beside the project's agent, from the same weights, on the same
batches and with the same random draws: one project update against the reference's
`train_policy` then `train_predictive_model` (what its training loop calls per minibatch with the
intrinsic rewards on), the project's scoring against its `get_intrinsic_values`, acting against
its `select_action_from_policy`, the initialisation against its `weight_init`, and the project's
defaults against the settings in its code and the argument defaults of its `train_loop.py`
(parsed, not imported: that file needs packages the project does not install).

The project holds none of the reference's code: `bench.reference` imports it from a checkout.
Set NASA_REFERENCE_DIR to one (git clone https://github.com/UoA-CARES/NaSA_TD3); without it
these tests are skipped.
"""

from __future__ import annotations

import ast
import inspect
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from bench import reference
from shared.agents import NaSATD3, make_agent
from shared.config import TrainConfig, agent_defaults
from shared.nets import weight_init

REFERENCE_DIR = os.environ.get("NASA_REFERENCE_DIR", "")
pytestmark = pytest.mark.skipif(not REFERENCE_DIR, reason="set NASA_REFERENCE_DIR to a checkout of "
                                                         "UoA-CARES/NaSA_TD3")

ACTION_DIM = 6
FRAME_STACK = 3
OBS_SHAPE = (3 * FRAME_STACK, 84, 84)  # the reference's networks are built for 84x84 frames only


def reference_order(agent: NaSATD3) -> torch.Tensor:
    """For each fc feature in the reference's order (conv output flattened (c, h, w)), its index in
    the project's order ((h, w, c): `shared.nets`)."""
    c, h, w = agent.encoder.conv_shape
    ours_of_ref = torch.arange(c * h * w).view(c, h, w).permute(1, 2, 0).flatten()
    return torch.argsort(ours_of_ref)


def paired(agent: NaSATD3, ref) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:  # noqa: ANN001
    """Every parameter of the reference's networks with the project's, in the reference's layout."""
    order = reference_order(agent)
    enc, dec = agent.encoder, agent.decoder
    pairs = {
        "encoder.fc.weight": (ref.encoder.fc.weight, enc.fc.weight[:, order]),
        "encoder.fc.bias": (ref.encoder.fc.bias, enc.fc.bias),
        "encoder.ln.weight": (ref.encoder.ln.weight, enc.ln.weight),
        "encoder.ln.bias": (ref.encoder.ln.bias, enc.ln.bias),
        "decoder.fc_1.weight": (ref.decoder.fc_1.weight, dec.fc.weight[order]),
        "decoder.fc_1.bias": (ref.decoder.fc_1.bias, dec.fc.bias[order]),
    }
    layers = [
        ("encoder.cov_net", list(ref.encoder.cov_net), [m for m in enc.convs if isinstance(m, nn.Conv2d)]),
        ("decoder.deconvs", [m for m in ref.decoder.deconvs if isinstance(m, nn.ConvTranspose2d)],
         [m for m in dec.deconvs if isinstance(m, nn.ConvTranspose2d)]),
    ]
    for name, theirs, ours in layers:
        for k, (a, b) in enumerate(zip(theirs, ours, strict=True)):
            pairs |= {f"{name}.{k}.{p}": (getattr(a, p), getattr(b, p)) for p in ("weight", "bias")}
    heads = [
        ("actor", ref.actor.act_net, agent.actor.net),
        ("actor_target", ref.actor_target.act_net, agent.actor_target.net),
        ("critic.Q1", ref.critic.Q1, agent.critic.q1),
        ("critic.Q2", ref.critic.Q2, agent.critic.q2),
        ("critic_target.Q1", ref.critic_target.Q1, agent.critic_target.q1),
        ("critic_target.Q2", ref.critic_target.Q2, agent.critic_target.q2),
        *[(f"epm.{i}", member.prediction_net, ours)
          for i, (member, ours) in enumerate(zip(ref.epm, agent.ensemble.members, strict=True))],
    ]
    for name, theirs, ours in heads:
        mine = dict(ours.named_parameters())
        pairs |= {f"{name}.{key}": (p, mine[key]) for key, p in theirs.named_parameters()}
    return pairs


@pytest.fixture
def agents():  # noqa: ANN201
    """The reference's agent at its loop's settings, and the project's with the same weights."""
    torch.manual_seed(0)
    ref = reference.make(Path(REFERENCE_DIR), ACTION_DIM, FRAME_STACK, torch.device("cpu"))
    config = agent_defaults("nasa_td3")
    config.latent_dim = reference.LATENT_SIZE
    agent = make_agent("nasa_td3", OBS_SHAPE, ACTION_DIM, config, torch.device("cpu"))
    pairs = paired(agent, ref)
    every = {id(p) for net in (ref.encoder, ref.decoder, ref.actor, ref.critic, ref.actor_target,
                               ref.critic_target, ref.epm) for p in net.parameters()}
    assert {id(theirs) for theirs, _ in pairs.values()} == every  # no parameter of theirs left out
    with torch.no_grad():
        for theirs, ours in pairs.values():
            theirs.copy_(ours)
    return agent, ref


def stacks(rng: np.random.Generator, size: int) -> np.ndarray:
    """Frame stacks with structure (blocks of 7x7 pixels) and fine noise, uint8."""
    coarse = rng.integers(0, 240, (size, OBS_SHAPE[0], 12, 12))
    fine = rng.integers(0, 16, (size, *OBS_SHAPE))
    return (coarse.repeat(7, axis=2).repeat(7, axis=3) + fine).astype(np.uint8)


def numpy_batch(seed: int, size: int = 8) -> dict[str, np.ndarray]:
    """Stored transitions: each next stack is its obs moved on by one new frame, some terminal."""
    rng = np.random.default_rng(seed)
    obs = stacks(rng, size)
    next_obs = np.concatenate([obs[:, 3:], stacks(rng, size)[:, :3]], axis=1)
    return {
        "obs": obs,
        "next_obs": next_obs,
        "action": rng.uniform(-1, 1, (size, ACTION_DIM)).astype(np.float32),
        "reward": rng.uniform(0, 1, size).astype(np.float32),
        "intrinsic": rng.uniform(0, 1, size).astype(np.float32),
        "discount": (rng.uniform(size=size) > 0.25).astype(np.float32),
    }


def test_an_update_is_the_references_train_policy_then_train_predictive_model(agents):
    agent, ref = agents
    # Adam divides each step by sqrt(v) + eps: with the default eps an element whose gradient is
    # within float32 round-off of 0 takes a step of up to the learning rate, of either sign, and
    # the two runs drift apart, as the reference drifts from itself when its weights are moved by a
    # rounding error. With eps raised alike in both, steps follow the gradients and round-off stays
    # round-off (the eps both use is checked in test_the_defaults_are_the_references).
    for opt in [*agent._optimizers().values(), ref.actor_optimizer, ref.critic_optimizer,
                ref.encoder_optimizer, ref.decoder_optimizer, *ref.epm_optimizers]:
        for group in opt.param_groups:
            group["eps"] = 1e-4
    before = agent.encoder.convs[0].weight.detach().clone()
    for update in range(1, 5):  # odd: critic, autoencoder, ensemble; even: the actor and targets too
        b = numpy_batch(update)
        torch.manual_seed(100 + update)  # the target policy's smoothing noise
        agent.update({key: torch.from_numpy(value) for key, value in b.items()})
        torch.manual_seed(100 + update)
        # The reference stores the environment's reward plus the bonus, and done for discount 0.
        dones = (b["discount"] == 0).astype(np.int64)
        ref.train_policy((b["obs"], b["action"], b["reward"] + b["intrinsic"], b["next_obs"], dones))
        ref.train_predictive_model((b["obs"], b["action"], b["next_obs"]))
        for name, (theirs, ours) in paired(agent, ref).items():
            where = f"{name} after update {update}"
            torch.testing.assert_close(ours, theirs.detach(), rtol=1e-4, atol=1e-6,
                                       msg=lambda m, where=where: f"{where}: {m}")
    assert not torch.equal(before, agent.encoder.convs[0].weight)  # the updates did train


def test_scores_are_the_references_get_intrinsic_values(agents):
    agent, ref = agents
    b = numpy_batch(0)
    ours = agent.score(*(torch.from_numpy(b[key]) for key in ("obs", "action", "next_obs")))
    for i in range(len(b["obs"])):
        surprise, novelty = ref.get_intrinsic_values(b["obs"][i], b["action"][i], b["next_obs"][i])
        np.testing.assert_allclose(float(ours["surprise"][i]), surprise, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(float(ours["novelty"][i]), novelty, rtol=0, atol=1e-4)  # as test_intrinsic
        # train_loop.py: reward_surprise * 1.0 + reward_novelty * 1.0 is added to the stored reward.
        np.testing.assert_allclose(float(ours["intrinsic"][i]), surprise + novelty, rtol=0, atol=1e-4)


def test_acting_is_the_references_select_action_from_policy(agents):
    """Evaluation: the policy's action; exploration: plus N(0, 0.1) noise, clipped to [-1, 1]. The
    reference draws its noise from numpy's global state, so the project's draws from it too here."""
    agent, ref = agents
    for obs in numpy_batch(0)["obs"][:4]:
        mine = agent.act(obs, explore=False, rng=np.random.default_rng(0))
        theirs = ref.select_action_from_policy(obs, evaluation=True)
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-6)
        np.random.seed(7)
        theirs = ref.select_action_from_policy(obs)
        np.random.seed(7)
        mine = agent.act(obs, explore=True, rng=np.random.mtrand._rand)
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-6)


def test_initialisation_is_the_references():
    """The reference's weight_init and the project's, on every kind of layer the networks have,
    draw the same weights from the same random state."""
    reference.load_class(Path(REFERENCE_DIR))
    reference_init = sys.modules["networks.weight_initialization"].weight_init

    def layers() -> nn.Sequential:
        return nn.Sequential(nn.Conv2d(9, 32, 3, stride=2), nn.ConvTranspose2d(32, 9, 3, stride=2),
                             nn.Linear(200, 1024), nn.Linear(1024, 6), nn.LayerNorm(200))

    theirs, ours = layers(), layers()
    torch.manual_seed(1)
    theirs.apply(reference_init)
    torch.manual_seed(1)
    ours.apply(weight_init)
    for (name, a), b in zip(theirs.state_dict().items(), ours.state_dict().values(), strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=0, msg=lambda m, name=name: f"{name}: {m}")


def train_loop_settings() -> dict[str, object]:
    """train_loop.py's argument defaults and the constants it assigns, read from its source."""
    script = Path(REFERENCE_DIR) / "train_loop.py"
    found = reference.argument_defaults(script)
    for node in ast.walk(ast.parse(script.read_text())):
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name) and isinstance(node.value, ast.Constant)):
            found[node.targets[0].id] = node.value.value
    return found


def test_the_defaults_are_the_references(agents):
    agent, ref = agents
    loop = train_loop_settings()
    train, c = TrainConfig(), agent_defaults("nasa_td3")
    ours = (train.steps, train.warmup_steps, train.batch_size, train.updates_per_step, train.eval_episodes)
    assert ours == (loop["max_steps_training"], loop["max_steps_pre_exploration"], loop["batch_size"],
                    loop["G"], loop["number_eval_episodes"])
    assert (c.latent_dim, train.env.frame_stack) == (loop["latent_size"], loop["number_stack_frames"])
    # train(): reward_surprise = surprise_rate * a, reward_novelty = novelty_rate * b.
    assert (c.surprise_weight, c.novelty_weight) == (loop["a"], loop["b"])
    assert (train.env.image_size, train.env.camera_id, train.env.action_repeat) == (84, 0, 1)  # FrameStack

    assert (c.gamma, c.tau, c.policy_delay, c.ensemble_size) == (
        ref.gamma, ref.tau, ref.policy_update_freq, ref.ensemble_size)
    assert (c.num_filters, c.num_conv_layers) == (ref.encoder.num_filters, ref.encoder.num_layers)
    assert [c.hidden_dim] * 2 == ref.actor.hidden_size == ref.critic.hidden_size
    assert [c.ensemble_hidden_dim] * 2 == ref.epm[0].hidden_size
    signature = inspect.signature(ref.select_action_from_policy)
    assert c.exploration_noise == signature.parameters["noise_scale"].default

    def settings(opt: torch.optim.Optimizer) -> tuple:
        group = opt.param_groups[0]
        return group["lr"], group["weight_decay"], group["betas"], group["eps"]

    pairs = [(agent.actor_opt, ref.actor_optimizer), (agent.critic_opt, ref.critic_optimizer),
             (agent.encoder_opt, ref.encoder_optimizer), (agent.decoder_opt, ref.decoder_optimizer),
             *[(agent.ensemble_opt, opt) for opt in ref.epm_optimizers]]
    for mine, theirs in pairs:
        assert settings(mine) == settings(theirs)
