"""SAC-AE against its reference's own code (denisyarats/pytorch_sac_ae), imported from a checkout.

tests/test_baselines_reference.py writes SAC-AE's update out by hand. Here the reference's
`SacAeAgent` itself, built with the argument defaults of its `train.py` (parsed, not imported: that
file needs dm_control and gym), runs beside the project's agent from the same weights, on the same
batches and with the same random draws: its `update` at the env steps `train.py` passes (a warm-up
burst, then one a step), its `select_action` and `sample_action`, its `weight_init` and the
initial state of its agent, and the project's defaults against its settings. Its `train.py` loop
itself runs beside `nasa train`, each with a stand-in that records which transitions each update may
sample and which policy picks each action.

The reference's `utils` imports gym, which the project does not install, for a frame-stack wrapper
these tests never use: where gym is missing, a module holding only `gym.Wrapper` stands in for it,
so nothing the agent computes comes from a stand-in. The project holds none of the reference's
code: `bench.reference` imports it from a checkout. Set SAC_AE_REFERENCE_DIR to one
(git clone https://github.com/denisyarats/pytorch_sac_ae); without it these tests are skipped.
"""

from __future__ import annotations

import contextlib
import importlib.util
import inspect
import math
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from bench import reference
from shared.agents import make_agent
from shared.agents.sac_ae import SACAE
from shared.config import agent_defaults, default_config
from shared.nets import weight_init

REFERENCE_DIR = os.environ.get("SAC_AE_REFERENCE_DIR", "")
pytestmark = pytest.mark.skipif(not REFERENCE_DIR, reason="set SAC_AE_REFERENCE_DIR to a checkout of "
                                                         "denisyarats/pytorch_sac_ae")

ACTION_DIM = 6
OBS_SHAPE = (9, 84, 84)  # the reference's encoder is built for 84x84 frames only (its OUT_DIM)


def train_py_settings() -> dict[str, object]:
    """train.py's argument defaults."""
    return reference.argument_defaults(Path(REFERENCE_DIR) / "train.py")


@pytest.fixture
def gym_stand_in(monkeypatch) -> None:  # noqa: ANN001
    """Where gym is missing, a module holding only `gym.Wrapper` in its place."""
    if importlib.util.find_spec("gym") is None:
        gym = types.ModuleType("gym")
        gym.Wrapper = object  # the base of utils.FrameStack, which no test here builds
        monkeypatch.setitem(sys.modules, "gym", gym)


@pytest.fixture
def sac_ae(gym_stand_in) -> types.ModuleType:  # noqa: ANN001
    """The reference's `sac_ae` module."""
    return reference.load_sac_ae(Path(REFERENCE_DIR))


def make_reference(sac_ae: types.ModuleType):  # noqa: ANN201
    """SacAeAgent as train.py's make_agent builds it at its argument defaults."""
    settings = train_py_settings()
    params = inspect.signature(sac_ae.SacAeAgent).parameters
    kwargs = {key: value for key, value in settings.items() if key in params}
    return sac_ae.SacAeAgent(OBS_SHAPE, (ACTION_DIM,), torch.device("cpu"), **kwargs)


def make_ours() -> SACAE:
    return make_agent("sac_ae", OBS_SHAPE, ACTION_DIM, agent_defaults("sac_ae"), torch.device("cpu"))


def reference_order(encoder: nn.Module) -> torch.Tensor:
    """For each fc feature in the reference's order (conv output flattened (c, h, w)), its index in
    the project's order ((h, w, c): `shared.nets`)."""
    c, h, w = encoder.conv_shape
    return torch.argsort(torch.arange(c * h * w).view(c, h, w).permute(1, 2, 0).flatten())


def paired(agent: SACAE, ref) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:  # noqa: ANN001
    """Every parameter of the reference's agent with the project's, in the reference's layout."""
    order = reference_order(agent.critic_encoder)
    pairs = {"log_alpha": (ref.log_alpha, agent.log_alpha)}
    encoders = [("critic.encoder", ref.critic.encoder, agent.critic_encoder),
                ("actor.encoder", ref.actor.encoder, agent.actor_encoder),
                ("critic_target.encoder", ref.critic_target.encoder, agent.critic_encoder_target)]
    for name, theirs, ours in encoders:
        convs = [m for m in ours.convs if isinstance(m, nn.Conv2d)]
        for k, (a, b) in enumerate(zip(theirs.convs, convs, strict=True)):
            pairs |= {f"{name}.convs.{k}.{p}": (getattr(a, p), getattr(b, p)) for p in ("weight", "bias")}
        pairs |= {f"{name}.fc.weight": (theirs.fc.weight, ours.fc.weight[:, order]),
                  f"{name}.fc.bias": (theirs.fc.bias, ours.fc.bias),
                  f"{name}.ln.weight": (theirs.ln.weight, ours.ln.weight),
                  f"{name}.ln.bias": (theirs.ln.bias, ours.ln.bias)}
    dec = agent.decoder
    pairs |= {"decoder.fc.weight": (ref.decoder.fc.weight, dec.fc.weight[order]),
              "decoder.fc.bias": (ref.decoder.fc.bias, dec.fc.bias[order])}
    deconvs = [m for m in dec.deconvs if isinstance(m, nn.ConvTranspose2d)]
    for k, (a, b) in enumerate(zip(ref.decoder.deconvs, deconvs, strict=True)):
        pairs |= {f"decoder.deconvs.{k}.{p}": (getattr(a, p), getattr(b, p)) for p in ("weight", "bias")}
    heads = [("actor.trunk", ref.actor.trunk, agent.actor.net),
             ("critic.Q1", ref.critic.Q1.trunk, agent.critic.q1),
             ("critic.Q2", ref.critic.Q2.trunk, agent.critic.q2),
             ("critic_target.Q1", ref.critic_target.Q1.trunk, agent.critic_target.q1),
             ("critic_target.Q2", ref.critic_target.Q2.trunk, agent.critic_target.q2)]
    for name, theirs, ours in heads:
        mine = dict(ours.named_parameters())
        pairs |= {f"{name}.{key}": (p, mine[key]) for key, p in theirs.named_parameters()}
    return pairs


@pytest.fixture
def agents(sac_ae):  # noqa: ANN001, ANN201
    """The reference's agent at train.py's settings, and the project's with the same weights."""
    torch.manual_seed(0)
    ref = make_reference(sac_ae)
    agent = make_ours()
    pairs = paired(agent, ref)
    nets = (ref.actor, ref.critic, ref.critic_target, ref.decoder)
    every = {id(p) for net in nets for p in net.parameters()}
    assert {id(theirs) for theirs, _ in pairs.values()} == every | {id(ref.log_alpha)}  # none left out
    with torch.no_grad():
        for theirs, ours in pairs.values():
            theirs.copy_(ours)
    return agent, ref


def numpy_batch(seed: int, size: int = 8) -> dict[str, np.ndarray]:
    """Stored transitions: frame stacks with structure (7x7 blocks) and fine noise, some terminal."""
    rng = np.random.default_rng(seed)

    def stacks() -> np.ndarray:
        coarse = rng.integers(0, 240, (size, OBS_SHAPE[0], 12, 12))
        return (coarse.repeat(7, axis=2).repeat(7, axis=3) + rng.integers(0, 16, (size, *OBS_SHAPE))
                ).astype(np.uint8)

    return {"obs": stacks(), "next_obs": stacks(),
            "action": rng.uniform(-1, 1, (size, ACTION_DIM)).astype(np.float32),
            "reward": rng.uniform(0, 1, size).astype(np.float32),
            "discount": (rng.uniform(size=size) > 0.25).astype(np.float32)}


class Replay:
    """The reference's ReplayBuffer.sample() of one batch: float frame stacks, (B, 1) columns."""

    def __init__(self, b: dict[str, np.ndarray]) -> None:
        self.b = b

    def sample(self) -> tuple[torch.Tensor, ...]:
        b = self.b
        column = lambda key: torch.from_numpy(b[key]).view(-1, 1)  # noqa: E731
        return (torch.from_numpy(b["obs"]).float(), torch.from_numpy(b["action"]), column("reward"),
                torch.from_numpy(b["next_obs"]).float(), column("discount"))


@contextlib.contextmanager
def noise_drawn_channels_last(monkeypatch):  # noqa: ANN001, ANN201
    """`torch.rand_like` (the dequantisation noise of the reference's `utils.preprocess_obs`) drawing
    its numbers in channels-last order, as it does on the project's channels-last frame stacks, so
    that each pixel gets the same draw in both; the numbers drawn are the same either way. (The
    reference's encoder cannot take channels-last stacks: it flattens them with `view`.)"""
    rand_like = torch.rand_like

    def drawn(x: torch.Tensor, **kwargs) -> torch.Tensor:  # noqa: ANN003
        if x.dim() != 4:
            return rand_like(x, **kwargs)
        return rand_like(x.contiguous(memory_format=torch.channels_last), **kwargs).contiguous()

    with monkeypatch.context() as patch:
        patch.setattr(torch, "rand_like", drawn)
        yield


class Silent:
    """The reference's Logger, recording nothing: its methods only log."""

    def __getattr__(self, name: str):  # noqa: ANN204
        return lambda *args, **kwargs: None


def test_updates_are_the_references_update_at_train_pys_steps(agents, monkeypatch):
    """train.py with 2 warm-up steps: 2 updates at env step 2 (both take an even step's path:
    critic, actor and alpha, targets, decoder), then one at each step 3, 4, 5."""
    agent, ref = agents
    # As in tests/test_nasa_reference.py: Adam's eps raised alike in both, so that a weight whose
    # gradient is within round-off of 0 does not take a step of up to the learning rate of either
    # sign in one run and not in the other (the eps both use is checked in the defaults test). What
    # round-off is left still grows from update to update, as the reference's does against itself
    # from weights moved by a rounding error; SAC-AE's learning rates are ten times NaSA-TD3's, and
    # so is the absolute tolerance here.
    for opt in [*agent._optimizers().values(), ref.actor_optimizer, ref.critic_optimizer,
                ref.log_alpha_optimizer, ref.encoder_optimizer, ref.decoder_optimizer]:
        for group in opt.param_groups:
            group["eps"] = 1e-4
    agent.burst_updates = 2
    before = agent.critic_encoder.convs[0].weight.detach().clone()
    for update, step in enumerate([2, 2, 3, 4, 5], start=1):
        b = numpy_batch(update)
        torch.manual_seed(100 + update)  # the policy's noise, the decoder target's dequantisation
        agent.update({key: torch.from_numpy(value) for key, value in b.items()})
        torch.manual_seed(100 + update)
        with noise_drawn_channels_last(monkeypatch):
            ref.update(Replay(b), Silent(), step)
        for name, (theirs, ours) in paired(agent, ref).items():
            where = f"{name} after update {update} (env step {step})"
            # .to: the reference's log_alpha is float64 (np.log's), the project's float32.
            torch.testing.assert_close(ours, theirs.detach().to(ours.dtype), rtol=1e-4, atol=1e-5,
                                       msg=lambda m, where=where: f"{where}: {m}")
    assert not torch.equal(before, agent.critic_encoder.convs[0].weight)  # the updates did train
    assert agent.log_alpha.item() != math.log(0.1)  # and so did the temperature


def test_acting_is_the_references_select_action_and_sample_action(agents):
    """Evaluation: the squashed mean; exploration: a squashed sample, its noise drawn alike."""
    agent, ref = agents
    for i, obs in enumerate(numpy_batch(0)["obs"][:4]):
        mine = agent.act(obs, explore=False, rng=np.random.default_rng(0))
        np.testing.assert_allclose(mine, ref.select_action(obs), rtol=0, atol=1e-6)
        torch.manual_seed(i)
        theirs = ref.sample_action(obs)
        torch.manual_seed(i)
        mine = agent.act(obs, explore=True, rng=np.random.default_rng(0))
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-6)
        assert not np.allclose(mine, ref.select_action(obs))  # the sample is not the mean


def test_initialisation_is_the_references(sac_ae):
    """The reference's weight_init and the project's draw the same weights from the same random
    state on every kind of layer; and each agent starts alike: every weight of the same
    distribution (the same zeros and, orthogonal, the same singular values), the targets equal to
    the critic, the actor's convolutions the critic's, the same temperature."""

    def layers() -> nn.Sequential:
        return nn.Sequential(nn.Conv2d(9, 32, 3, stride=2), nn.ConvTranspose2d(32, 9, 3, stride=2),
                             nn.Linear(50, 1024), nn.Linear(1024, 12), nn.LayerNorm(50))

    theirs, ours = layers(), layers()
    torch.manual_seed(1)
    theirs.apply(sac_ae.weight_init)
    torch.manual_seed(1)
    ours.apply(weight_init)
    for (name, a), b in zip(theirs.state_dict().items(), ours.state_dict().values(), strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=0, msg=lambda m, name=name: f"{name}: {m}")

    torch.manual_seed(0)
    ref, agent = make_reference(sac_ae), make_ours()
    for name, (a, b) in paired(agent, ref).items():
        a, b = a.detach().to(b.dtype), b.detach()
        assert torch.equal(a == 0, b == 0), name
        if a.dim() == 4:  # delta-orthogonal: the centre taps are orthogonal
            a, b = a[:, :, 1, 1], b[:, :, 1, 1]
        if a.dim() == 2:
            torch.testing.assert_close(torch.linalg.svdvals(b), torch.linalg.svdvals(a), rtol=1e-4, atol=1e-5,
                                       msg=lambda m, name=name: f"{name}: {m}")
        elif name.endswith("ln.weight") or name == "log_alpha":
            torch.testing.assert_close(b, a, rtol=0, atol=1e-7)
    for net, target in [(ref.critic, ref.critic_target), (agent.critic, agent.critic_target),
                        (agent.critic_encoder, agent.critic_encoder_target)]:
        for p, q in zip(net.parameters(), target.parameters(), strict=True):
            assert torch.equal(p, q)
    assert ref.actor.encoder.convs[0].weight is ref.critic.encoder.convs[0].weight
    assert agent.actor_encoder.convs[0].weight is agent.critic_encoder.convs[0].weight
    assert agent.target_entropy == ref.target_entropy


def test_the_defaults_are_train_pys(agents):
    agent, ref = agents
    s, c = train_py_settings(), agent_defaults("sac_ae")
    train = default_config("sac_ae", "paper")
    assert (train.steps, train.warmup_steps, train.batch_size, train.replay_capacity) == (
        s["num_train_steps"], s["init_steps"], s["batch_size"], s["replay_buffer_capacity"])
    assert (train.eval_every, train.eval_episodes) == (s["eval_freq"], s["num_eval_episodes"])
    # train.py: one update per env step, and init_steps of them at the step that ends the warm-up.
    assert (train.updates_per_step, train.warmup_burst) == (1, True)
    env = train.env
    assert (env.image_size, env.action_repeat, env.frame_stack) == (
        s["image_size"], s["action_repeat"], s["frame_stack"])
    assert (c.latent_dim, c.hidden_dim, c.num_filters, c.num_conv_layers) == (
        s["encoder_feature_dim"], s["hidden_dim"], s["num_filters"], s["num_layers"])
    assert (c.gamma, c.tau, c.encoder_tau, c.init_temperature) == (
        s["discount"], s["critic_tau"], s["encoder_tau"], s["init_temperature"])
    # --policy-delay is both of SAC-AE's schedules: the actor's and the targets'.
    assert c.policy_delay == s["actor_update_freq"] == s["critic_target_update_freq"]
    assert s["decoder_update_freq"] == 1  # the project's autoencoder steps at every update
    assert (c.log_std_min, c.log_std_max) == (s["actor_log_std_min"], s["actor_log_std_max"])
    assert c.decoder_latent_lambda == s["decoder_latent_lambda"] == ref.decoder_latent_lambda
    assert (s["encoder_type"], s["decoder_type"]) == ("pixel", "pixel")

    def settings(opt: torch.optim.Optimizer) -> tuple:
        group = opt.param_groups[0]
        return group["lr"], group["weight_decay"], group["betas"], group["eps"]

    pairs = [(agent.actor_opt, ref.actor_optimizer), (agent.critic_opt, ref.critic_optimizer),
             (agent.alpha_opt, ref.log_alpha_optimizer), (agent.encoder_opt, ref.encoder_optimizer),
             (agent.decoder_opt, ref.decoder_optimizer)]
    for mine, theirs in pairs:
        assert settings(mine) == settings(theirs)


class ActionSpace:
    """The stand-in environment's action space: its uniform draw is one of train.py's random actions."""

    def __init__(self, sampled) -> None:  # noqa: ANN001
        self.shape, self.low, self.high = (ACTION_DIM,), -np.ones(ACTION_DIM), np.ones(ACTION_DIM)
        self.sampled = sampled

    def sample(self) -> np.ndarray:
        self.sampled()
        return np.zeros(ACTION_DIM, np.float32)


class Episodes:
    """dmc2gym's environment in train.py, stood in for: blank frames, episodes of 5 steps."""

    _max_episode_steps = 5

    def __init__(self, sampled) -> None:  # noqa: ANN001
        self.observation_space = types.SimpleNamespace(shape=(3, 4, 4))
        self.action_space = ActionSpace(sampled)
        self.t = 0

    def seed(self, seed: int) -> None:
        pass

    def reset(self) -> np.ndarray:
        self.t = 0
        return np.zeros(self.observation_space.shape, np.uint8)

    def step(self, action: np.ndarray) -> tuple:
        self.t += 1
        return np.zeros(self.observation_space.shape, np.uint8), 0.0, self.t == self._max_episode_steps, {}


class Recording:
    """train.py's agent, stood in for: it records what the loop has it do, as
    tests.test_reference_loop.sac_ae_reference_events writes it, on the loop's own replay buffer."""

    training = True

    def __init__(self, events: list[tuple], replay) -> None:  # noqa: ANN001
        self.events, self.replay, self.updates = events, replay, 0

    def train(self, training: bool = True) -> None:  # utils.eval_mode's
        self.training = training

    def sample_action(self, obs: np.ndarray) -> np.ndarray:
        self.events.append(("act", False, self.replay["buffer"].idx, self.updates))
        return np.zeros(ACTION_DIM, np.float32)

    def select_action(self, obs: np.ndarray) -> np.ndarray:  # evaluation's, which stores nothing
        return np.zeros(ACTION_DIM, np.float32)

    def update(self, replay_buffer, logger, step: int) -> None:  # noqa: ANN001
        self.events.append(("update", replay_buffer.idx, self.updates))
        self.updates += 1


def train_py_events(monkeypatch, work_dir: Path, steps: int, init_steps: int) -> list[tuple]:  # noqa: ANN001
    """train.py's `main()` itself, run for `steps` steps with `init_steps`: its replay buffer is its
    own; its environment and agent record what it has them do, where its Logger and VideoRecorder
    (which import packages the project does not install) record nothing, and its frame stack (a
    gym wrapper) leaves the stand-in's frames as they are."""
    events: list[tuple] = []
    replay: dict[str, object] = {}
    agent = Recording(events, replay)
    env = Episodes(lambda: events.append(("act", True, replay["buffer"].idx, agent.updates)))
    stand_ins = {"dmc2gym": types.SimpleNamespace(make=lambda **kwargs: env),
                 "logger": types.SimpleNamespace(Logger=lambda *args, **kwargs: Silent()),
                 "video": types.SimpleNamespace(VideoRecorder=lambda *args, **kwargs: Silent())}
    for name, module in stand_ins.items():
        monkeypatch.setitem(sys.modules, name, module)
    own = ("train", *(name.removesuffix(".py") for name in reference.SAC_AE_FILES))
    train = reference.import_from(Path(REFERENCE_DIR), "train", own)
    for name in own:  # as bench.reference.load_sac_ae: names as common as utils leave sys.modules
        sys.modules.pop(name, None)
    real_buffer = train.utils.ReplayBuffer

    def buffer(**kwargs):  # noqa: ANN003, ANN202
        replay["buffer"] = real_buffer(**kwargs)
        return replay["buffer"]

    monkeypatch.setattr(train.utils, "ReplayBuffer", buffer)
    monkeypatch.setattr(train.utils, "FrameStack", lambda env, k: env)
    monkeypatch.setattr(train, "make_agent", lambda *args, **kwargs: agent)
    monkeypatch.setattr(sys, "argv", ["train.py", "--init_steps", str(init_steps),
                                      "--num_train_steps", str(steps), "--replay_buffer_capacity", "100",
                                      "--num_eval_episodes", "1", "--work_dir", str(work_dir)])
    torch_state, numpy_state = torch.get_rng_state(), np.random.get_state()
    try:
        train.main()
    finally:  # its set_seed_everywhere seeded this process's generators
        torch.set_rng_state(torch_state)
        np.random.set_state(numpy_state)
    return events


def test_nasa_train_acts_and_updates_on_the_rows_train_pys_loop_does(tmp_path, monkeypatch, gym_stand_in):
    """train.py's loop run with 3 warm-up steps beside `nasa train --algo sac_ae` with 3: the same
    random steps, each update on a replay of as many stored transitions (its burst on the warm-up's
    3, before the step that makes it stores its own), and each action picked by the policy of as
    many updates (the initial policy's at the burst's step). tests/test_reference_loop.py checks
    the same sequence without the reference, written out as sac_ae_reference_events, which this
    checks is train.py's."""
    from tests.test_reference_loop import nasa_train_events, sac_ae_reference_events, sac_ae_run

    steps, init_steps = 9, 3
    theirs = train_py_events(monkeypatch, tmp_path / "reference", steps, init_steps)
    trainer = sac_ae_run(tmp_path / "run", steps, warmup=init_steps)
    ours = nasa_train_events(trainer, monkeypatch)
    trainer.run()
    assert ours == theirs
    assert theirs == sac_ae_reference_events(steps, init_steps)
    assert ("update", init_steps, 0) in theirs  # the burst, on the warm-up's transitions
