"""Gradient routing, targets, updates and state round trips of every agent."""

import copy

import numpy as np
import pytest
import torch

from shared.agents import SACAE, TD3, TD3AE, NaSATD3, PixelTD3, UnscoredBatchError, make_agent
from shared.agents.base import float_pixels
from shared.config import ALGOS, agent_defaults
from shared.nets import float_channels_last, relu_, sigmoid_mse

OBS_SHAPE = (9, 48, 48)
ACTION_DIM = 2
# Small widths keep these tests fast; the routing does not depend on them.
SMALL = {"latent_dim": 32, "hidden_dim": 64, "ensemble_hidden_dim": 32, "num_filters": 16}


def make(algo: str, obs_shape=OBS_SHAPE, small: bool = True, **overrides):
    config = agent_defaults(algo)
    for key, value in ({**SMALL, **overrides} if small else overrides).items():
        setattr(config, key, value)
    return make_agent(algo, obs_shape, ACTION_DIM, config, torch.device("cpu"))


def random_batch(batch_size: int = 8, seed: int = 0, obs_shape=OBS_SHAPE) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.randint(0, 256, (batch_size, *obs_shape), dtype=torch.uint8, generator=g),
        "next_obs": torch.randint(0, 256, (batch_size, *obs_shape), dtype=torch.uint8, generator=g),
        "action": torch.rand(batch_size, ACTION_DIM, generator=g) * 2 - 1,
        "reward": torch.rand(batch_size, generator=g),
        "discount": torch.ones(batch_size),
        "intrinsic": torch.rand(batch_size, generator=g),
    }


def snapshot(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone() for name, p in module.named_parameters()}


def changed(before: dict[str, torch.Tensor], module: torch.nn.Module) -> set[str]:
    return {name for name, p in module.named_parameters() if not torch.equal(before[name], p)}


def encoder_groups(names: set[str]) -> set[str]:
    """conv / fc / ln: which parts of an encoder a set of parameter names touches."""
    return {"conv" if n.startswith("convs") else n.split(".")[0] for n in names}


@pytest.mark.parametrize("algo", ["nasa_td3", "td3_ae", "pixel_td3"])
def test_critic_loss_moves_whole_encoder_and_q_heads_only(algo):
    agent = make(algo)
    batch = random_batch()
    q_target = agent.td_target(batch["reward"].view(-1, 1), batch["discount"].view(-1, 1), batch["next_obs"])
    enc, critic, actor = snapshot(agent.encoder), snapshot(agent.critic), snapshot(agent.actor)
    targets = snapshot(agent.critic_target)
    agent.update_critic(batch["obs"], batch["action"], q_target)
    assert encoder_groups(changed(enc, agent.encoder)) == {"conv", "fc", "ln"}
    assert changed(critic, agent.critic) == set(critic)
    assert changed(actor, agent.actor) == set()
    assert changed(targets, agent.critic_target) == set()


@pytest.mark.parametrize("algo", ["nasa_td3", "td3_ae", "pixel_td3"])
def test_actor_loss_leaves_every_encoder_parameter(algo):
    agent = make(algo)
    batch = random_batch()
    enc, critic, actor = snapshot(agent.encoder), snapshot(agent.critic), snapshot(agent.actor)
    agent.update_actor(agent.encoder(batch["obs"]))  # not detached here: the method must detach
    assert changed(enc, agent.encoder) == set()
    assert changed(critic, agent.critic) == set()
    assert changed(actor, agent.actor) == set(actor)
    assert all(p.grad is None for p in agent.encoder.parameters())  # no gradient reached it


@pytest.mark.parametrize("algo", ["nasa_td3", "td3_ae"])
def test_autoencoder_loss_moves_encoder_and_decoder_not_heads(algo):
    agent = make(algo)
    batch = random_batch()
    enc, dec, critic = snapshot(agent.encoder), snapshot(agent.decoder), snapshot(agent.critic)
    agent.update_autoencoder(batch["obs"])
    assert encoder_groups(changed(enc, agent.encoder)) == {"conv", "fc", "ln"}
    assert changed(dec, agent.decoder) == set(dec)
    assert changed(critic, agent.critic) == set()


def test_ensemble_loss_moves_ensemble_only():
    agent = make("nasa_td3")
    batch = random_batch()
    enc, ens = snapshot(agent.encoder), snapshot(agent.ensemble)
    agent.update_ensemble(batch["obs"], batch["action"], batch["next_obs"])
    assert changed(enc, agent.encoder) == set()
    assert changed(ens, agent.ensemble) == set(ens)


@pytest.mark.parametrize("every", [1, 3])
def test_ensemble_trains_on_every_nth_update(every):
    agent = make("nasa_td3", ensemble_every=every)
    batch = random_batch()
    moved = []
    for _ in range(6):
        before = snapshot(agent.ensemble)
        metrics = agent.update(batch)
        moved.append(bool(changed(before, agent.ensemble)))
        assert ("ensemble_loss" in metrics) == moved[-1]
    assert moved == [(n + 1) % every == 0 for n in range(6)]


def test_one_adam_over_members_equals_one_per_member():
    agent = make("nasa_td3")
    batch = random_batch()
    reference = copy.deepcopy(agent.ensemble)
    opts = [
        torch.optim.Adam(m.parameters(), lr=1e-4, weight_decay=1e-3) for m in reference.members
    ]
    with torch.no_grad():
        z = agent.encoder(batch["obs"])
        z_next = agent.encoder(batch["next_obs"])
    for member, opt in zip(reference.members, opts, strict=True):
        loss = torch.nn.functional.mse_loss(member(torch.cat([z, batch["action"]], 1)), z_next)
        opt.zero_grad()
        loss.backward()
        opt.step()
    agent.update_ensemble(batch["obs"], batch["action"], batch["next_obs"])
    for a, b in zip(reference.parameters(), agent.ensemble.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_targets_hold_no_encoder_and_read_the_online_one():
    agent = make("nasa_td3")
    for target in (agent.actor_target, agent.critic_target):
        assert not any(isinstance(m, torch.nn.Conv2d) for m in target.modules())
    batch = random_batch()
    args = (batch["reward"].view(-1, 1), batch["discount"].view(-1, 1), batch["next_obs"])
    torch.manual_seed(0)
    before = agent.td_target(*args)
    with torch.no_grad():
        # change only the online encoder (not by a scale: LayerNorm would undo it)
        agent.encoder.fc.weight.add_(0.1 * torch.randn_like(agent.encoder.fc.weight))
    torch.manual_seed(0)
    assert not torch.allclose(before, agent.td_target(*args))


def test_soft_update_moves_heads_at_policy_delay_only():
    agent = make("td3_ae")
    batch = random_batch()
    target_actor = snapshot(agent.actor_target)
    agent.update(batch)  # update 1: no actor step, no target update
    assert changed(target_actor, agent.actor_target) == set()
    metrics = agent.update(batch)  # update 2: actor + targets
    assert "actor_loss" in metrics
    assert changed(target_actor, agent.actor_target) == set(target_actor)


@pytest.mark.parametrize("algo", ALGOS)
def test_one_update_of_every_agent(algo):
    """At the reference's full size: 84x84 stacks, its widths."""
    agent = make(algo, obs_shape=(9, 84, 84), small=False)
    batch = random_batch(batch_size=4, obs_shape=(9, 84, 84))
    for _ in range(2):
        metrics = agent.update(batch)
    assert agent.num_updates == 2
    assert all(np.isfinite(v) for v in metrics.values())
    expected = {"critic_loss", "actor_loss"}
    if algo != "pixel_td3":
        expected.add("ae_loss")
    if algo == "nasa_td3":
        expected.add("ensemble_loss")
    assert expected <= set(metrics)


def test_sac_ae_actor_loss_leaves_critic_convs():
    agent = make("sac_ae")
    batch = random_batch()
    agent.num_updates = 1  # the next update runs the actor
    conv = snapshot(agent.critic_encoder.convs)
    agent.critic_opt.step = lambda *a, **k: None  # isolate: the critic step would move convs
    agent.encoder_opt.step = lambda *a, **k: None
    actor_fc = snapshot(agent.actor_encoder.fc)
    agent.update(batch)
    assert changed(conv, agent.critic_encoder.convs) == set()
    assert changed(actor_fc, agent.actor_encoder.fc) == set(actor_fc)  # the actor's own fc learns
    assert agent.actor_encoder.convs[0].weight is agent.critic_encoder.convs[0].weight


@pytest.mark.parametrize("algo", ALGOS)
def test_state_round_trip_gives_same_action_and_update(algo):
    agent = make(algo)
    batch = random_batch()
    agent.update(batch)
    clone = make(algo)
    clone.load_state_dict(copy.deepcopy(agent.state_dict()))
    obs = batch["obs"][0].numpy()
    rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
    torch.manual_seed(3)
    a = agent.act(obs, explore=True, rng=rng_a)
    torch.manual_seed(3)
    b = clone.act(obs, explore=True, rng=rng_b)
    np.testing.assert_array_equal(a, b)
    torch.manual_seed(5)
    metrics_a = agent.update(random_batch(seed=1))
    torch.manual_seed(5)
    metrics_b = clone.update(random_batch(seed=1))
    assert metrics_a == metrics_b
    for (name, p), q in zip(agent.state_dict().items(), clone.state_dict().values(), strict=True):
        if isinstance(p, dict) and "state" not in p:
            for k in p:
                torch.testing.assert_close(p[k], q[k], rtol=0, atol=0, msg=f"{name}.{k}")


def test_policy_weights_round_trip():
    agent, actor_copy = make("nasa_td3"), make("nasa_td3")
    actor_copy.load_policy_state_dict(agent.policy_state_dict())
    obs = random_batch()["obs"][0].numpy()
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(
        agent.act(obs, explore=False, rng=rng), actor_copy.act(obs, explore=False, rng=rng)
    )


def test_actions_are_bounded():
    agent = make("nasa_td3", exploration_noise=5.0)
    obs = random_batch()["obs"][0].numpy()
    action = agent.act(obs, explore=True, rng=np.random.default_rng(0))
    assert action.shape == (ACTION_DIM,) and np.all(np.abs(action) <= 1.0)


# What a checkpoint holds per algorithm: the names existing checkpoints were saved under.
TD3_KEYS = {"encoder", "actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt",
            "num_updates"}
CHECKPOINT_KEYS = {
    "pixel_td3": TD3_KEYS,
    "td3_ae": TD3_KEYS | {"decoder", "encoder_opt", "decoder_opt"},
    "nasa_td3": TD3_KEYS | {"decoder", "encoder_opt", "decoder_opt", "ensemble", "ensemble_opt"},
    "sac_ae": {
        "critic_encoder", "actor_encoder", "critic", "actor", "critic_encoder_target", "critic_target",
        "decoder", "actor_opt", "critic_opt", "alpha_opt", "encoder_opt", "decoder_opt", "log_alpha",
        "num_updates",
    },
}


@pytest.mark.parametrize(
    ("algo", "cls"), [("nasa_td3", NaSATD3), ("td3_ae", TD3AE), ("pixel_td3", PixelTD3), ("sac_ae", SACAE)]
)
def test_each_algorithm_is_its_own_class_with_its_checkpoint_keys(algo, cls):
    agent = make(algo)
    assert type(agent) is cls and agent.algo == algo
    assert set(agent.state_dict()) == CHECKPOINT_KEYS[algo]
    assert {k.split(".")[0] for k in agent.policy_state_dict()} == {"encoder", "actor"}
    assert agent.uses_intrinsic == (algo == "nasa_td3")


def test_pixel_td3_is_td3_alone():
    agent = make("pixel_td3")
    assert isinstance(agent, TD3) and not isinstance(agent, TD3AE)
    assert not hasattr(agent, "decoder") and not hasattr(agent, "ensemble")
    with pytest.raises(RuntimeError, match="no intrinsic rewards"):
        agent.score(*(random_batch()[k] for k in ("obs", "action", "next_obs")))


def test_a_collect_update_refuses_unscored_rows_and_changes_nothing():
    agent = make("nasa_td3")
    batch = random_batch()
    batch["intrinsic"][[1, 4, 6]] = float("nan")
    before = copy.deepcopy(agent.state_dict())
    with pytest.raises(UnscoredBatchError, match="3 of 8 rows of the batch have no intrinsic score") as err:
        agent.update(batch)
    assert isinstance(err.value, ValueError)
    assert agent.num_updates == 0
    for name, module in agent._modules().items():
        for key, value in module.state_dict().items():
            assert torch.equal(value, before[name][key]), f"{name}.{key}"
    batch["intrinsic"] = torch.nan_to_num(batch["intrinsic"])
    agent.update(batch)  # once scored, the same batch updates
    assert agent.num_updates == 1


@pytest.mark.parametrize(("algo", "timing"), [
    ("nasa_td3", "fresh"), ("td3_ae", "collect"), ("pixel_td3", "collect"), ("sac_ae", "collect"),
])
def test_agents_that_store_no_score_ignore_the_intrinsic_column(algo, timing):
    agent = make(algo, intrinsic_timing=timing)
    batch = random_batch()
    batch["intrinsic"] = torch.full((8,), float("nan"))
    for _ in range(2):
        metrics = agent.update(batch)
    assert all(np.isfinite(v) for v in metrics.values())


def test_fresh_timing_rescores_and_collect_reads_the_batch():
    fresh, collect = make("nasa_td3", intrinsic_timing="fresh"), make("nasa_td3")
    batch = random_batch()
    batch["intrinsic"] = torch.full((8,), 123.0)
    assert collect.update(batch)["intrinsic_batch_mean"] == pytest.approx(123.0)
    assert fresh.update(batch)["intrinsic_batch_mean"] != pytest.approx(123.0)


@pytest.mark.parametrize("shared_encoder_pass", [False, True])
def test_a_fresh_update_scores_with_the_encoder_passes_it_makes_anyway(shared_encoder_pass):
    # Scoring, the TD target and the critic read the same weights: one Enc(obs) and one
    # Enc(next_obs) serve all three, with the same result as computing each apart.
    shared, apart, collect = (
        make("nasa_td3", intrinsic_timing=t, shared_encoder_pass=shared_encoder_pass)
        for t in ("fresh", "fresh", "collect")
    )
    for other in (apart, collect):
        other.load_state_dict(shared.state_dict())
    scoring = type(apart).score_with_next_latent
    # Ignoring the given latent and returning none: scoring and the TD target encode themselves.
    apart.score_with_next_latent = lambda obs, action, next_obs, latent=None, chain=True: (
        scoring(apart, obs, action, next_obs)[0], None)
    passes = {}
    for agent in (shared, apart, collect):
        passes[agent] = 0
        agent.encoder.register_forward_pre_hook(
            lambda module, args, agent=agent: passes.__setitem__(agent, passes[agent] + 1)
        )
        torch.manual_seed(3)
        agent.update(random_batch())
    assert passes[shared] == passes[collect]  # fresh scoring costs no encoder pass of its own
    assert passes[apart] == passes[shared] + 1  # scoring apart: obs and next_obs in one pass
    for name, value in apart.encoder.state_dict().items():
        torch.testing.assert_close(shared.encoder.state_dict()[name], value)
    for name, value in apart.critic.state_dict().items():
        torch.testing.assert_close(shared.critic.state_dict()[name], value)


def test_fc_layers_are_the_references_up_to_a_fixed_relabelling_of_conv_features():
    # The reference flattens conv features in (c, h, w) order; ours are read in (h, w, c)
    # order (channels-last, no copy). Permuting fc's weights between the two orders
    # must give the very same encoder and decoder outputs.
    torch.manual_seed(0)
    agent = make_agent("td3_ae", (9, 84, 84), 2, agent_defaults("td3_ae"), torch.device("cpu"))
    encoder, decoder = agent.encoder, agent.decoder
    c, h, w = encoder.conv_shape
    ours_of_ref = torch.arange(c * h * w).view(c, h, w).permute(1, 2, 0).flatten()  # our index i holds ref's
    ref_of_ours = torch.argsort(ours_of_ref)
    obs = torch.randint(0, 256, (3, 9, 84, 84), dtype=torch.uint8)
    with torch.no_grad():
        conv = encoder.convs(obs.float()).flatten(1)  # the reference's (c, h, w) flatten
        ref_fc = torch.nn.functional.linear(conv, encoder.fc.weight[:, ref_of_ours], encoder.fc.bias)
        z = torch.tanh(encoder.ln(ref_fc))
        assert torch.allclose(encoder(obs), z, atol=1e-5)

        ref_h = torch.relu(torch.nn.functional.linear(
            z, decoder.fc.weight[ref_of_ours], decoder.fc.bias[ref_of_ours]
        )).view(-1, c, h, w)
        ref_reconstruction = torch.sigmoid(decoder.deconvs(ref_h))
        assert torch.allclose(decoder(z), ref_reconstruction, atol=1e-5)


@pytest.mark.parametrize("precision, dtype", [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_an_update_casts_each_stack_batch_once_and_the_encoder_reads_it_without_a_copy(precision, dtype):
    batch = random_batch()
    cast = float_pixels(batch, precision)
    for key in ("obs", "next_obs"):
        assert batch[key].dtype == torch.uint8  # the caller's batch is left as it was
        assert cast[key].dtype == dtype
        assert cast[key].is_contiguous(memory_format=torch.channels_last)
        assert torch.equal(cast[key].float(), batch[key].float())  # pixels are exact in bfloat16 too
        assert float_channels_last(cast[key], dtype) is cast[key]  # later passes read it as it is
    for key in ("action", "reward", "discount", "intrinsic"):
        assert cast[key] is batch[key]
    agent = make("nasa_td3", pixel_precision=precision)
    assert torch.equal(agent.encoder(batch["obs"]), agent.encoder(cast["obs"]))


@pytest.mark.parametrize(
    "algo, timing, precision",
    [
        ("nasa_td3", "collect", "fp32"),
        ("nasa_td3", "fresh", "fp32"),
        ("sac_ae", "collect", "fp32"),
        ("nasa_td3", "fresh", "bf16"),
    ],
)
def test_an_update_on_a_cast_batch_equals_one_on_the_uint8_batch(algo, timing, precision):
    agent = make(algo, intrinsic_timing=timing, pixel_precision=precision)
    twin = copy.deepcopy(agent)
    batch = random_batch()
    torch.manual_seed(1)  # the TD target's smoothing noise
    metrics = agent.update(batch)
    torch.manual_seed(1)
    assert twin.update(float_pixels(batch, precision)) == metrics
    for (name, mine), (_, theirs) in zip(agent._modules().items(), twin._modules().items(), strict=True):
        for p, q in zip(mine.parameters(), theirs.parameters(), strict=True):
            assert torch.equal(p, q), name


def conv_output_dtypes(agent) -> list[torch.dtype]:
    """The dtypes the agent's convolutions compute in (their outputs'), recorded by hooks."""
    seen: list[torch.dtype] = []
    for module in agent._modules().values():
        for layer in module.modules():
            if isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
                layer.register_forward_hook(lambda m, args, out: seen.append(out.dtype))
    return seen


@pytest.mark.parametrize("algo", ["nasa_td3", "td3_ae", "pixel_td3", "sac_ae"])
def test_bf16_pixel_precision_runs_the_pixel_networks_in_bf16_and_keeps_the_rest_fp32(algo):
    fp32, bf16 = make(algo), make(algo, pixel_precision="bf16")
    bf16.load_state_dict(copy.deepcopy(fp32.state_dict()))
    seen = conv_output_dtypes(bf16)
    batch = random_batch(16)
    bf16.update(batch)
    assert seen and set(seen) == {torch.bfloat16}
    # Parameters and optimizer states stay float32; the checkpoint loads into an fp32 agent.
    state = bf16.state_dict()
    tensors = [t for t in _tensors(state) if t.is_floating_point()]
    assert tensors and all(t.dtype == torch.float32 for t in tensors)
    make(algo).load_state_dict(copy.deepcopy(state))
    # Same functions up to bf16 rounding: latents and reconstructions of the same weights agree.
    obs = random_batch(16, seed=1)["obs"]
    with torch.no_grad():
        fp32.load_state_dict(copy.deepcopy(state))
        encoder = "critic_encoder" if algo == "sac_ae" else "encoder"
        z32, z16 = getattr(fp32, encoder)(obs), getattr(bf16, encoder)(obs)
        assert z16.dtype == torch.float32
        assert torch.allclose(z16, z32, atol=0.05) and not torch.equal(z16, z32)
        if hasattr(bf16, "decoder"):
            r32, r16 = fp32.decoder(z32), bf16.decoder(z32)
            assert r16.dtype == torch.float32
            assert torch.allclose(r16, r32, atol=0.05) and not torch.equal(r16, r32)


def test_the_bfloat16_relu_outside_autograd_gives_torchs_relu_for_every_bfloat16():
    """`relu_` clamps untracked bfloat16 maps through their int16 bits; tracked ones take torch's
    ReLU, with its gradient."""
    values = torch.arange(-32768, 32768, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)
    numbers = ~torch.isnan(values)  # every finite and infinite bfloat16
    got = relu_(values.clone())
    assert torch.equal(got[numbers].float(), torch.relu(values[numbers].float()))
    x = torch.randn(64).bfloat16().requires_grad_()
    relu_(x * 1).sum().backward()
    assert torch.equal(x.grad, (x > 0).to(torch.bfloat16))


def test_an_unknown_pixel_precision_fails_when_the_agent_is_made():
    with pytest.raises(ValueError, match="unknown pixel precision 'fp16'"):
        make("nasa_td3", pixel_precision="fp16")


def test_bf16_pixel_precision_learns_what_fp32_learns_on_a_fixed_batch():
    """Updates on one batch of blocky images lower the autoencoder's loss alike in both formats."""
    batch = random_batch(16)
    g = torch.Generator().manual_seed(2)
    coarse = torch.randint(0, 256, (16, OBS_SHAPE[0], 6, 6), dtype=torch.uint8, generator=g)
    batch["obs"] = coarse.repeat_interleave(8, dim=2).repeat_interleave(8, dim=3)
    losses = {}
    for precision in ("fp32", "bf16"):
        torch.manual_seed(0)
        agent = make("td3_ae", pixel_precision=precision, encoder_lr=1e-3, decoder_lr=1e-3)
        metrics = [agent.update(batch) for _ in range(60)]
        losses[precision] = (metrics[0]["ae_loss"], metrics[-1]["ae_loss"])
    for first, last in losses.values():
        assert last < 0.8 * first
    assert losses["bf16"][-1] == pytest.approx(losses["fp32"][-1], rel=0.05)


def _tensors(tree):
    if isinstance(tree, torch.Tensor):
        yield tree
    elif isinstance(tree, dict):
        for value in tree.values():
            yield from _tensors(value)
    elif isinstance(tree, list | tuple):
        for value in tree:
            yield from _tensors(value)


@pytest.mark.parametrize("channels_last_layout", [False, True])
def test_the_fused_reconstruction_loss_is_sigmoid_then_mse(channels_last_layout):
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(4, 9, 20, 20, generator=g) * 3
    pixels = torch.randint(0, 256, (4, 9, 20, 20), generator=g).float()
    if channels_last_layout:
        logits = logits.contiguous(memory_format=torch.channels_last)
        pixels = pixels.contiguous(memory_format=torch.channels_last)
    a, b = logits.clone().requires_grad_(), logits.clone().requires_grad_()
    expected = torch.nn.functional.mse_loss(torch.sigmoid(a), pixels / 255.0)
    got = sigmoid_mse(b, pixels)
    expected.backward(torch.tensor(3.0))
    got.backward(torch.tensor(3.0))
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=0.0)
    torch.testing.assert_close(b.grad, a.grad, rtol=1e-5, atol=1e-9)  # grads up to ~1e-4
