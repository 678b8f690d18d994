"""Typed configuration: one home for every default.

The defaults are the settings of the NaSA-TD3 reference implementation;
SAC-AE's own settings live in `SAC_AE_OVERRIDES` (its training loop's in
`SAC_AE_TRAIN_OVERRIDES`), the cheaper settings of a CPU run in `PRESETS`.
`nasa train`, `nasa up` and every service read their flags through
`shared.service.parse_with_preset`, so each default is declared here and
nowhere else. `validate()` rejects bad values with a clear message before any
work starts.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

from shared.gl import RENDER_QUALITIES, RenderQuality

Algo = Literal["nasa_td3", "td3_ae", "pixel_td3", "sac_ae"]
ALGOS: tuple[str, ...] = ("nasa_td3", "td3_ae", "pixel_td3", "sac_ae")
DEFAULT_PRESET = "auto"
PIXEL_PRECISIONS: tuple[str, ...] = ("fp32", "bf16")


class ConfigError(ValueError):
    """A configuration value that cannot work."""


# The evaluation environment's seed is the run's seed plus this, in every process that evaluates.
EVAL_SEED_OFFSET = 1_000_000


@dataclass
class EnvConfig:
    task: str = "ball_in_cup-catch"
    """A task of an environment source (shared.envs): for the DeepMind Control Suite
    `domain-task`, e.g. cheetah-run. The default is a paper task whose untrained policy scores 0,
    so a first run shows what it learned (with repeated actions cartpole-balance's untrained
    policy already keeps the pole up)."""
    image_size: int = 84
    frame_stack: int = 3
    action_repeat: int = 1
    camera_id: int = 0
    render_quality: RenderQuality = "paper"
    """`paper`: the suite's scene as is; `fast`: 512 shadow map, no multisampling; `plain`:
    `fast` without shadows or floor reflections (`shared.gl.apply_render_quality`)."""
    time_limit: Literal["bootstrap", "terminal"] = "terminal"
    """`terminal` (the NaSA-TD3 reference's): store the suite's time-limit ending with discount 0;
    `bootstrap`: keep the suite's discount 1 there and bootstrap through it, as SAC-AE does."""


@dataclass
class AgentConfig:
    latent_dim: int = 200
    num_filters: int = 32
    num_conv_layers: int = 4
    hidden_dim: int = 1024
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    """The critic's optimizer also holds the encoder (the reference does this on purpose)."""
    encoder_lr: float = 1e-4
    decoder_lr: float = 1e-4
    decoder_weight_decay: float = 1e-7
    decoder_latent_lambda: float = 1e-6
    ensemble_size: int = 5
    ensemble_hidden_dim: int = 512
    ensemble_lr: float = 1e-4
    ensemble_weight_decay: float = 1e-3
    ensemble_every: int = 1
    """Train the ensemble on every n-th update. 1 (default): at every update, on the
    critic's minibatch, as the reference's current code does. `updates_per_step` (G):
    once per env step, on the last of its G minibatches, the schedule of the
    reference's revisions of mid-2023."""
    gamma: float = 0.99
    tau: float = 0.005
    """Soft-update rate of the Q heads and actor MLP (TD3) or of the critic (SAC-AE)."""
    policy_delay: int = 2
    target_noise: float = 0.2
    target_noise_clip: float = 0.5
    exploration_noise: float = 0.1
    novelty_weight: float = 1.0
    """alpha in R = R_ext + alpha * R_novel + beta * R_surprise."""
    surprise_weight: float = 1.0
    """beta in R = R_ext + alpha * R_novel + beta * R_surprise."""
    intrinsic_timing: Literal["collect", "fresh"] = "collect"
    """`collect`: scored once when stored (the paper); `fresh`: rescored at each sampling."""
    shared_encoder_pass: bool = False
    """Faster, not the reference: encode each batch once for critic and autoencoder
    (the reference encodes again after the critic step)."""
    pixel_precision: Literal["fp32", "bf16"] = "fp32"
    """Number format of the encoder's and decoder's convolutions and linear layers:
    `fp32` (the reference) or `bf16`, mixed precision (bfloat16 products, float32
    sums, parameters, heads, losses and optimizer states); faster where the hardware
    has bfloat16 units (recent x86 CPUs, GPUs from Ampere on), not the reference."""
    random_shift: int = 0
    """Pixels by which each frame stack of a batch is moved at random in an update (DrQ's random
    shift augmentation, `shared.augment`); 0 (default, the reference): none."""
    cuda_graph: bool = False
    """Replay each update as a captured CUDA graph (CUDA only): one launch instead of hundreds of
    small kernels, each from Python; the same arithmetic, not the reference's way of running it."""
    # SAC-AE only.
    encoder_tau: float = 0.05
    init_temperature: float = 0.1
    alpha_lr: float = 1e-4
    alpha_beta: float = 0.5
    actor_beta: float = 0.9
    critic_beta: float = 0.9
    log_std_min: float = -10.0
    log_std_max: float = 2.0


SAC_AE_OVERRIDES: dict[str, object] = {
    "latent_dim": 50,
    "actor_lr": 1e-3,
    "critic_lr": 1e-3,
    "encoder_lr": 1e-3,
    "decoder_lr": 1e-3,
    "tau": 0.01,
}
# SAC-AE's training loop where it differs from NaSA-TD3's reference: one update per env step
# (G = 5 is NaSA-TD3's) after a burst as many as the warm-up's steps, each step's updates before
# its transition is stored, its buffer draws with replacement, and it bootstraps through the time
# limit.
SAC_AE_TRAIN_OVERRIDES: dict[str, object] = {
    "updates_per_step": 1,
    "warmup_burst": True,
    "updates_before_store": True,
    "env.time_limit": "bootstrap",
    "sample_without_replacement": False,
}


_TD3 = ("nasa_td3", "td3_ae", "pixel_td3")
_AE = ("nasa_td3", "td3_ae", "sac_ae")
# The agent fields only some algorithms read; every other field applies to all of them.
FIELD_ALGOS: dict[str, tuple[str, ...]] = {
    **dict.fromkeys(("target_noise", "target_noise_clip", "exploration_noise"), _TD3),
    **dict.fromkeys(("encoder_lr", "decoder_lr", "decoder_weight_decay", "decoder_latent_lambda"), _AE),
    "shared_encoder_pass": ("nasa_td3", "td3_ae"),
    **dict.fromkeys(("ensemble_size", "ensemble_hidden_dim", "ensemble_lr", "ensemble_weight_decay",
                     "ensemble_every", "novelty_weight", "surprise_weight", "intrinsic_timing"),
                    ("nasa_td3",)),
    **dict.fromkeys(("encoder_tau", "init_temperature", "alpha_lr", "alpha_beta", "actor_beta",
                     "critic_beta", "log_std_min", "log_std_max"), ("sac_ae",)),
}


def inert_flags(algo: str, flags: set[str]) -> list[str]:
    """Lines naming each of `flags` (`--target-noise`, `--no-shared-encoder-pass`) that sets an
    agent field `algo` does not read, so a user learns the flag changed nothing."""
    lines = []
    for name, algos in FIELD_ALGOS.items():
        flag = "--" + name.replace("_", "-")
        given = sorted(flags & {flag, "--no-" + flag[2:]})
        if given and algo not in algos:
            lines.append(f"{given[0]} does nothing under --algo {algo}: only {', '.join(algos)} read it")
    return lines


def agent_defaults(algo: str) -> AgentConfig:
    """The reference settings of one algorithm."""
    check_algo(algo)
    config = AgentConfig()
    if algo == "sac_ae":
        config = dataclasses.replace(config, **SAC_AE_OVERRIDES)
    return config


@dataclass
class TrainConfig:
    algo: Algo = "nasa_td3"
    seed: int = 0
    steps: int = 1_000_000
    """Environment steps (agent decisions, after action repeat)."""
    warmup_steps: int = 1_000
    """Uniform random steps before learning starts."""
    updates_per_step: int = 5
    """G: gradient updates per environment step after warm-up."""
    warmup_burst: bool = False
    """SAC-AE's warm-up burst: the first step after warm-up makes `warmup_steps` updates in place of
    its G, as SAC-AE's reference does (the default of `--algo sac_ae`). Off, the NaSA-TD3
    reference's way: G updates from the first step after warm-up on."""
    updates_before_store: bool = False
    """Make each step's updates before its transition is stored, as SAC-AE's reference does (the
    default of `--algo sac_ae`): an update samples the transitions of the steps before its own.
    Off, the NaSA-TD3 reference's way: a step's transition is stored, then its updates."""
    batch_size: int = 128
    sample_without_replacement: bool = True
    """Draw each batch without repeated rows, as the NaSA-TD3 reference does; off draws rows
    independently (with replacement), as SAC-AE does. The two differ only while the replay is
    small."""
    replay_capacity: int = 1_000_000
    replay_compression: Literal["lz4", "zstd"] = "lz4"
    """Replay frame compressor: lz4 decodes faster, zstd stores fewer bytes."""
    eval_every: int = 10_000
    eval_episodes: int = 10
    eval_at_start: bool = True
    """Evaluate the untrained policy at step 0; False reproduces the reference, whose
    first evaluation comes after `eval_every` steps."""
    eval_same_episodes: bool = False
    """Every evaluation plays the same episodes: the evaluation environment's draws (initial
    states; the gripper's targets and reset angles) start each evaluation where they stood when
    it was made, so successive evaluations differ by the policy alone. False, the reference's
    way: each evaluation goes on drawing where the last one stopped."""
    checkpoint_every: int = 10_000
    device: str = "auto"
    """`cpu`, `cuda`, `cuda:N` or `auto` (cuda when present)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)


def check_algo(algo: str) -> None:
    if algo not in ALGOS:
        raise ConfigError(f"unknown algo {algo!r}; choose one of {', '.join(ALGOS)}")


MAX_IMAGE_SIZE = 480
MIN_IMAGE_SIZE = 7
"""The SSIM window (shared.ssim_kernel.WIN) of the novelty and surprise scores."""


def check_types(config: TrainConfig) -> None:
    """Each field holds a value of its type: a hand-written config.json's "300" or null would
    otherwise fail deep in a run, and its "yes" would read as true. A float field takes a whole
    number too, as JSON writes 1.0; bools are not numbers here."""
    for prefix, section in (("", config), ("env.", config.env), ("agent.", config.agent)):
        for f in dataclasses.fields(section):
            value, name = getattr(section, f.name), prefix + f.name
            if f.type == "bool" and not isinstance(value, bool):
                raise ConfigError(f"{name} must be true or false, got {value!r}")
            number = isinstance(value, int | float) and not isinstance(value, bool)
            if f.type == "int" and not (number and isinstance(value, int)):
                raise ConfigError(f"{name} must be a whole number, got {value!r}")
            if f.type == "float" and not (number and math.isfinite(value)):
                raise ConfigError(f"{name} must be a finite number, got {value!r}")
            if f.type == "str" and not isinstance(value, str):
                raise ConfigError(f"{name} must be a string, got {value!r}")


def conv_output_size(image_size: int, num_conv_layers: int) -> int:
    """Height (and width) of the encoder's conv stack output (shared.nets.Encoder): a 3x3
    stride-2 convolution, then 3x3 stride-1 ones, none padded."""
    return (image_size - 3) // 2 + 1 - 2 * (num_conv_layers - 1)


def validate(config: TrainConfig) -> TrainConfig:
    """Reject values that cannot work, naming the field and the rule."""
    check_algo(config.algo)
    positive = {
        "steps": config.steps,
        "updates_per_step": config.updates_per_step,
        "batch_size": config.batch_size,
        "replay_capacity": config.replay_capacity,
        "eval_every": config.eval_every,
        "eval_episodes": config.eval_episodes,
        "checkpoint_every": config.checkpoint_every,
        "env.image_size": config.env.image_size,
        "env.frame_stack": config.env.frame_stack,
        "env.action_repeat": config.env.action_repeat,
        "agent.latent_dim": config.agent.latent_dim,
        "agent.num_filters": config.agent.num_filters,
        "agent.num_conv_layers": config.agent.num_conv_layers,
        "agent.hidden_dim": config.agent.hidden_dim,
        "agent.ensemble_size": config.agent.ensemble_size,
        "agent.ensemble_hidden_dim": config.agent.ensemble_hidden_dim,
        "agent.policy_delay": config.agent.policy_delay,
        "agent.ensemble_every": config.agent.ensemble_every,
    }
    check_types(config)
    for name, value in positive.items():
        if value < 1:
            raise ConfigError(f"{name} must be >= 1, got {value}")
    if config.warmup_steps < 0:
        raise ConfigError(f"warmup_steps must be >= 0, got {config.warmup_steps}")
    if config.updates_before_store and not config.warmup_burst and config.warmup_steps == 0:
        raise ConfigError("updates_before_store with warmup_steps 0 makes the first step's updates on an "
                          "empty replay: give warmup_steps >= 1, or --warmup-burst (its burst of 0 "
                          "updates leaves the first update to the second step)")
    if not 0 <= config.seed < 2**32:  # numpy's and MuJoCo's seeds are unsigned 32-bit
        raise ConfigError(f"seed must be in [0, 2**32 - 1], got {config.seed}")
    if config.env.image_size > MAX_IMAGE_SIZE:
        raise ConfigError(f"env.image_size must be <= {MAX_IMAGE_SIZE} (the height of the suite's "
                          f"offscreen frame buffer), got {config.env.image_size}")
    if conv_output_size(config.env.image_size, config.agent.num_conv_layers) < 1:
        raise ConfigError(
            f"env.image_size {config.env.image_size} is too small for {config.agent.num_conv_layers} "
            f"conv layers: they need at least {4 * config.agent.num_conv_layers - 1} pixels"
        )
    if config.env.image_size < MIN_IMAGE_SIZE:
        raise ConfigError(f"env.image_size must be >= {MIN_IMAGE_SIZE} (the SSIM window of the novelty "
                          f"score), got {config.env.image_size}")
    if config.env.camera_id < 0:
        raise ConfigError(f"env.camera_id must be >= 0 (a camera of the task's model), "
                          f"got {config.env.camera_id}")
    from shared.wire import MAX_BATCH  # imports numpy: not at the top, which --help reads

    if config.batch_size > MAX_BATCH:
        raise ConfigError(
            f"batch_size must be <= {MAX_BATCH}, got {config.batch_size}: the replay service refuses "
            "larger sample requests, so the distributed runner (nasa up) would stall; nasa train "
            "shares the config, and its limit")
    first_fill = min(config.warmup_steps, config.replay_capacity)  # what the replay holds at the first update
    if config.sample_without_replacement and first_fill < config.batch_size:
        raise ConfigError(
            f"sample_without_replacement draws batch_size ({config.batch_size}) distinct transitions, "
            f"so the replay must hold that many at the first update: warmup_steps ({config.warmup_steps}) "
            f"and replay_capacity ({config.replay_capacity}) must each be >= batch_size, or draw "
            "with replacement (--no-sample-without-replacement)")
    agent = config.agent
    for name in ("actor_lr", "critic_lr", "encoder_lr", "decoder_lr", "ensemble_lr", "alpha_lr"):
        value = getattr(agent, name)
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"agent.{name} must be a finite number > 0, got {value}")
    for name in ("gamma", "tau", "encoder_tau"):
        value = getattr(agent, name)
        if not (0.0 < value <= 1.0):
            raise ConfigError(f"agent.{name} must be in (0, 1], got {value}")
    for name in (
        "target_noise", "target_noise_clip", "exploration_noise", "novelty_weight",
        "surprise_weight", "decoder_weight_decay", "decoder_latent_lambda",
        "ensemble_weight_decay", "init_temperature",
    ):
        value = getattr(agent, name)
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"agent.{name} must be a finite number >= 0, got {value}")
    for name in ("alpha_beta", "actor_beta", "critic_beta"):  # Adam's beta1 of SAC-AE's optimizers
        value = getattr(agent, name)
        if not 0.0 <= value < 1.0:
            raise ConfigError(f"agent.{name} must be in [0, 1), got {value}")
    if not agent.log_std_min < agent.log_std_max:
        raise ConfigError(f"agent.log_std_min ({agent.log_std_min}) must be below agent.log_std_max "
                          f"({agent.log_std_max})")
    if agent.intrinsic_timing not in ("collect", "fresh"):
        raise ConfigError(f"agent.intrinsic_timing must be collect or fresh, got {agent.intrinsic_timing!r}")
    if agent.pixel_precision not in PIXEL_PRECISIONS:
        choices = ", ".join(PIXEL_PRECISIONS)
        raise ConfigError(f"agent.pixel_precision must be one of {choices}, got {agent.pixel_precision!r}")
    shift = agent.random_shift
    if isinstance(shift, bool) or not isinstance(shift, int) or not 0 <= shift <= config.env.image_size // 4:
        raise ConfigError(
            f"agent.random_shift must be a whole number of pixels from 0 to a quarter of the image "
            f"({config.env.image_size // 4}), got {shift!r}"
        )
    if config.env.render_quality not in RENDER_QUALITIES:
        choices = ", ".join(RENDER_QUALITIES)
        raise ConfigError(f"env.render_quality must be one of {choices}, got {config.env.render_quality!r}")
    if config.env.time_limit not in ("bootstrap", "terminal"):
        raise ConfigError(f"env.time_limit must be bootstrap or terminal, got {config.env.time_limit!r}")
    if config.replay_compression not in ("lz4", "zstd"):
        raise ConfigError(f"replay_compression must be lz4 or zstd, got {config.replay_compression!r}")
    return config


def to_dict(config: TrainConfig) -> dict:
    return dataclasses.asdict(config)


def from_dict(data: dict) -> TrainConfig:
    data = dict(data)
    env = EnvConfig(**data.pop("env", {}))
    agent = AgentConfig(**data.pop("agent", {}))
    return TrainConfig(env=env, agent=agent, **data)


# A preset changes what costs (image size, widths, batch, G, action repeat) and keeps
# the method: autoencoder, intrinsic rewards and TD3 as they are (cpu-small also bootstraps
# through the time limit, said where it sets it).
PRESETS: dict[str, dict[str, object]] = {
    "paper": {},
    "cpu-small": {
        "steps": 50_000,
        "updates_per_step": 1,
        "batch_size": 64,
        "warmup_steps": 500,
        "eval_every": 1_000,
        "eval_episodes": 5,
        "checkpoint_every": 5_000,
        "replay_capacity": 100_000,
        "env.image_size": 64,
        "env.action_repeat": 8,
        "env.render_quality": "plain",
        "agent.latent_dim": 50,
        "agent.hidden_dim": 256,
        "agent.ensemble_hidden_dim": 128,
        "agent.num_conv_layers": 2,
        "agent.num_filters": 16,
        # Repeating each action 8 times makes an episode 125 decisions, so a terminal at the time
        # limit would cut most of an episode's return at the discount's horizon; the suite's
        # discount of 1 there is bootstrapped instead, and the batch is drawn with replacement as
        # as every measured run of this preset did.
        "env.time_limit": "bootstrap",
        "sample_without_replacement": False,
    },
}
PRESET_NAMES = ("auto", *PRESETS)

# A preset's per-task variants, by task-name prefix: what a task's own definition fixes over the
# preset. The gripper's 50-step episodes are the paper's task only at one action per step. Its
# target is drawn per episode, so a policy that ignores it still scores anywhere from 0 to -50 an
# episode: five episodes cannot tell learning from luck; twenty can, and every 2,000 steps they take
# about the share of the run that the suite tasks' evaluations take. The walker and the cheetah
# repeat each action as the field's pixel agents do on them (PlaNet, SAC-AE, DrQ): 8 is too coarse
# a control for a gait. The gripper's markers still show at 32x32, where an update costs a third of
# one at 64x64, and from its pixels the agent gains within the preset's time only with DrQ's random
# shift (docs/benchmarks.md, the gripper stand-in).
TASK_VARIANTS: dict[str, dict[str, dict[str, object]]] = {
    "cpu-small": {
        "gripper-": {
            "env.action_repeat": 1, "eval_episodes": 20, "eval_every": 2_000,
            "env.image_size": 32, "agent.random_shift": 2,
        },
        "walker-": {"env.action_repeat": 2},
        "cheetah-": {"env.action_repeat": 4},
    },
}


def apply_preset(config: TrainConfig, preset: str, task: str | None = None) -> TrainConfig:
    """A copy of `config` with the preset's values set, and its variant for `task` (default: the
    config's task) where it has one."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESET_NAMES)}")
    config = from_dict(to_dict(config))
    task = config.env.task if task is None else task
    values = dict(PRESETS[preset])
    for prefix, variant in TASK_VARIANTS.get(preset, {}).items():
        if task.startswith(prefix):
            values |= variant
    set_fields(config, values, f"preset {preset!r}")
    return config


def set_fields(config: TrainConfig, values: dict[str, object], owner: str) -> None:
    """Set `values`, keyed by dotted field names (`env.image_size`), on `config` in place."""
    for key, value in values.items():
        target = config
        *parents, name = key.split(".")
        for parent in parents:
            target = getattr(target, parent)
        if not hasattr(target, name):
            raise ConfigError(f"{owner} sets unknown field {key!r}")
        setattr(target, name, value)


def auto_preset(device_type: str) -> str:
    """The paper's settings on a GPU; on a CPU they are too slow to train, so the small preset."""
    return "paper" if device_type == "cuda" else "cpu-small"


def default_config(algo: str, preset: str, task: str | None = None) -> TrainConfig:
    """Reference settings of `algo` with a preset (and its variant for `task`) applied."""
    config = TrainConfig(algo=algo, agent=agent_defaults(algo))  # type: ignore[arg-type]
    if algo == "sac_ae":
        set_fields(config, SAC_AE_TRAIN_OVERRIDES, "SAC-AE's settings")
    return apply_preset(config, preset, task)
