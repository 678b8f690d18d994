"""Config validation, device choice, task names, frame stacking and render quality."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from shared import envs
from shared.config import (
    ALGOS,
    PRESETS,
    ConfigError,
    TrainConfig,
    agent_defaults,
    apply_preset,
    default_config,
    from_dict,
    to_dict,
    validate,
)
from shared.device import DeviceError, resolve_device


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("batch_size", 0, "batch_size must be >= 1"),
        ("steps", -5, "steps must be >= 1"),
        ("warmup_steps", -1, "warmup_steps must be >= 0"),
        ("agent.gamma", 1.5, r"agent.gamma must be in \(0, 1\]"),
        ("agent.critic_lr", float("nan"), "agent.critic_lr must be a finite number"),
        ("agent.exploration_noise", -0.1, "exploration_noise must be a finite number >= 0"),
        ("agent.intrinsic_timing", "later", "intrinsic_timing must be collect or fresh"),
        ("env.render_quality", "ultra", "render_quality must be one of paper, fast, plain"),
        ("agent.pixel_precision", "fp16", "pixel_precision must be one of fp32, bf16"),
        ("replay_compression", "brotli", "replay_compression must be lz4 or zstd"),
        ("env.time_limit", "never", "time_limit must be bootstrap or terminal"),
        ("env.image_size", 8, "too small"),
        ("env.image_size", 481, r"env.image_size must be <= 480 .* got 481"),
        ("seed", -5, r"seed must be in \[0, 2\*\*32 - 1\], got -5"),
        ("seed", 2**32, r"seed must be in .* got 4294967296"),
        ("algo", "dqn", "unknown algo 'dqn'"),
        ("agent.cuda_graph", "no", "agent.cuda_graph must be true or false, got 'no'"),
        ("agent.shared_encoder_pass", 1, "agent.shared_encoder_pass must be true or false"),
        ("eval_same_episodes", None, "eval_same_episodes must be true or false"),
        ("agent.random_shift", -1, r"random_shift must be a whole number of pixels .* \(21\), got -1"),
        ("agent.random_shift", 22, r"random_shift .* got 22"),
        ("agent.random_shift", 2.5, r"random_shift .* got 2.5"),
        ("agent.random_shift", True, r"random_shift .* got True"),
        ("steps", "300", "steps must be a whole number, got '300'"),
        ("seed", None, "seed must be a whole number, got None"),
        ("batch_size", 64.5, "batch_size must be a whole number, got 64.5"),
        ("env.frame_stack", True, "env.frame_stack must be a whole number, got True"),
        ("agent.tau", "0.1", "agent.tau must be a finite number, got '0.1'"),
        ("agent.log_std_max", float("inf"), "agent.log_std_max must be a finite number, got inf"),
        ("env.task", 5, "env.task must be a string, got 5"),
        ("agent.alpha_beta", 1.0, r"agent.alpha_beta must be in \[0, 1\), got 1.0"),
        ("agent.actor_beta", -0.1, r"agent.actor_beta must be in \[0, 1\)"),
        ("agent.critic_beta", 1.5, r"agent.critic_beta must be in \[0, 1\)"),
        ("agent.log_std_min", 2.0, r"agent.log_std_min \(2.0\) must be below agent.log_std_max \(2.0\)"),
        ("env.camera_id", -1, "env.camera_id must be >= 0"),
        ("batch_size", 4097, "batch_size must be <= 4096, got 4097: the replay service refuses"),
    ],
)
def test_bad_values_are_rejected_with_a_clear_message(path, value, message):
    config = TrainConfig()
    target = config
    *parents, name = path.split(".")
    for parent in parents:
        target = getattr(target, parent)
    setattr(target, name, value)
    with pytest.raises(ConfigError, match=message):
        validate(config)


def test_a_whole_number_is_a_float_fields_value_too():
    config = TrainConfig()
    config.agent.gamma, config.agent.log_std_min = 1, -10  # JSON may write 1.0 as 1
    validate(config)


def test_sampling_without_replacement_needs_a_batch_in_the_replay_at_the_first_update():
    config = TrainConfig(sample_without_replacement=True, batch_size=128, warmup_steps=127)
    with pytest.raises(ConfigError, match=r"warmup_steps \(127\) and replay_capacity .* >= batch_size"):
        validate(config)
    config.warmup_steps, config.replay_capacity = 1000, 100
    with pytest.raises(ConfigError, match="sample_without_replacement draws batch_size"):
        validate(config)
    config.replay_capacity = 128
    validate(config)
    validate(TrainConfig(sample_without_replacement=False, warmup_steps=0))  # with replacement: any


@pytest.mark.parametrize("layers", [1, 2, 4, 5, 6, 8])
def test_the_image_size_bound_is_the_encoders_at_its_edge(layers):
    from shared.config import MIN_IMAGE_SIZE
    from shared.nets import Decoder, Encoder
    from shared.ssim_kernel import WIN

    assert MIN_IMAGE_SIZE == WIN
    smallest = max(4 * layers - 1, MIN_IMAGE_SIZE)
    config = TrainConfig()
    config.agent.num_conv_layers, config.env.image_size = layers, smallest
    validate(config)
    encoder = Encoder((3, smallest, smallest), 8, num_filters=4, num_layers=layers)
    Decoder((3, smallest, smallest), encoder.conv_shape, 8, num_filters=4, num_layers=layers)
    config.env.image_size = smallest - 1
    with pytest.raises(ConfigError, match="too small|must be >= 7"):
        validate(config)
    if smallest - 1 < 4 * layers - 1:  # the conv stack's own edge: torch refuses what validate does
        with pytest.raises(RuntimeError):
            Encoder((3, smallest - 1, smallest - 1), 8, num_filters=4, num_layers=layers)


def test_defaults_are_the_reference_settings():
    c = TrainConfig()
    a = agent_defaults("nasa_td3")
    assert (c.batch_size, c.updates_per_step, c.warmup_steps, c.eval_every, c.eval_episodes) == (
        128, 5, 1000, 10_000, 10,
    )
    assert (c.env.image_size, c.env.frame_stack, c.env.action_repeat) == (84, 3, 1)
    assert (a.latent_dim, a.hidden_dim, a.actor_lr, a.critic_lr, a.encoder_lr, a.decoder_lr) == (
        200, 1024, 1e-4, 1e-3, 1e-4, 1e-4,
    )
    assert (a.ensemble_size, a.ensemble_hidden_dim, a.ensemble_weight_decay) == (5, 512, 1e-3)
    assert (a.gamma, a.tau, a.policy_delay, a.target_noise, a.target_noise_clip) == (
        0.99, 0.005, 2, 0.2, 0.5,
    )
    assert a.intrinsic_timing == "collect"
    assert c.env.time_limit == "terminal" and c.sample_without_replacement  # the reference's
    assert a.random_shift == 0  # the reference augments nothing
    sac = agent_defaults("sac_ae")
    assert (sac.latent_dim, sac.actor_lr, sac.tau, sac.encoder_tau, sac.init_temperature) == (
        50, 1e-3, 0.01, 0.05, 0.1,
    )


def test_sac_ae_makes_one_update_per_env_step_as_its_training_loop_does():
    from nasa.cli import parse_train

    assert default_config("sac_ae", "paper").updates_per_step == 1
    assert default_config("td3_ae", "paper").updates_per_step == 5  # NaSA-TD3's G for its own family
    cmd, _, _ = parse_train(["--algo", "sac_ae", "--preset", "paper"])
    assert cmd.config.updates_per_step == 1
    cmd, _, _ = parse_train(["--algo", "sac_ae", "--preset", "paper", "--updates-per-step", "5"])
    assert cmd.config.updates_per_step == 5


@pytest.mark.parametrize("field", ["warmup_burst", "updates_before_store"])
def test_only_sac_ae_takes_its_loops_order_by_default_and_the_flags_set_it(field: str) -> None:
    """SAC-AE's train.py bursts at the end of its warm-up and makes a step's updates before it
    stores the step's transition; NaSA-TD3's train_loop.py makes G updates from the first step
    after warm-up, each after the step is stored, and so do the algorithms run in its loop."""
    from nasa.cli import parse_train

    flag = "--" + field.replace("_", "-")
    for algo in ALGOS:
        for preset in PRESETS:
            assert getattr(default_config(algo, preset), field) == (algo == "sac_ae"), (algo, preset)
    cmd, _, _ = parse_train(["--algo", "sac_ae", "--preset", "paper", flag.replace("--", "--no-", 1)])
    assert not getattr(cmd.config, field)
    cmd, _, _ = parse_train(["--algo", "nasa_td3", "--preset", "paper", flag])
    assert getattr(cmd.config, field)


def test_updates_before_store_needs_a_stored_transition_for_the_first_updates() -> None:
    """Before a step is stored, the first updates need a transition already stored."""
    config = TrainConfig(sample_without_replacement=False, warmup_steps=0, updates_before_store=True)
    with pytest.raises(ConfigError, match="updates_before_store with warmup_steps 0 makes the first "
                                          "step's updates on an empty replay"):
        validate(config)
    config.warmup_burst = True  # a burst of 0 updates: the first update is the second step's
    validate(config)


def test_presets_touch_only_existing_fields_and_round_trip():
    for name in PRESETS:
        config = apply_preset(TrainConfig(), name)
        validate(config)
        assert from_dict(to_dict(config)) == config
    small = default_config("nasa_td3", "cpu-small")
    assert small.env.image_size < 84 and small.agent.ensemble_size == 5  # method kept
    with pytest.raises(ConfigError, match="unknown preset"):
        apply_preset(TrainConfig(), "huge")


def test_a_preset_has_per_task_variants_and_flags_still_win():
    from nasa.cli import parse_train

    # cpu-small repeats actions 8 times on the suite's tasks; the gripper's task is one action a step
    assert default_config("nasa_td3", "cpu-small", "ball_in_cup-catch").env.action_repeat == 8
    assert default_config("nasa_td3", "cpu-small", "gripper-valve_reset").env.action_repeat == 1
    assert default_config("nasa_td3", "paper", "gripper-valve").env.action_repeat == 1
    # the gaits repeat as the field's pixel agents do; the paper's settings repeat nothing
    assert default_config("nasa_td3", "cpu-small", "walker-walk").env.action_repeat == 2
    assert default_config("nasa_td3", "cpu-small", "cheetah-run").env.action_repeat == 4
    assert default_config("nasa_td3", "paper", "walker-walk").env.action_repeat == 1
    # its evaluations: more episodes (a random target each), half as often
    gripper = default_config("nasa_td3", "cpu-small", "gripper-valve")
    assert (gripper.eval_episodes, gripper.eval_every) == (20, 2_000)
    # and smaller frames, shifted at random in each update (its pixel agent gains only so in 30 minutes)
    assert (gripper.env.image_size, gripper.agent.random_shift) == (32, 2)
    assert default_config("nasa_td3", "paper", "gripper-valve").agent.random_shift == 0
    suite = default_config("nasa_td3", "cpu-small", "ball_in_cup-catch")
    assert (suite.eval_episodes, suite.eval_every) == (5, 1_000)
    cmd, _, _ = parse_train(["--preset", "cpu-small", "--task", "gripper-valve"])
    assert cmd.config.env.action_repeat == 1 and cmd.config.agent.latent_dim == 50  # the rest is the preset's
    cmd, _, _ = parse_train(["--preset", "cpu-small", "--task", "gripper-valve", "--random-shift", "0"])
    assert cmd.config.agent.random_shift == 0 and cmd.config.env.image_size == 32
    cmd, _, _ = parse_train(["--preset", "cpu-small", "--task", "gripper-valve", "--action-repeat", "2"])
    assert cmd.config.env.action_repeat == 2


@pytest.mark.parametrize("command", ["train", "up"])
def test_every_config_field_has_a_cli_flag(command, capsys):
    from nasa.cli import main
    from shared.config import AgentConfig, EnvConfig

    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    help_text = capsys.readouterr().out
    for cls in (TrainConfig, EnvConfig, AgentConfig):
        for f in dataclasses.fields(cls):
            if f.name in ("env", "agent"):
                continue
            assert f"--{f.name.replace('_', '-')}" in help_text, f.name


def test_device_errors_are_clear():
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type in ("cpu", "cuda")
    with pytest.raises(DeviceError, match="unknown device"):
        resolve_device("tpu9")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="CUDA is not available"):
            resolve_device("cuda")


FREE_A_LARGE_BLOCK = """
import sys
import torch
from shared.device import resolve_device
if sys.argv[1] == "cpu":
    resolve_device("cpu")
page = 4096
def resident_mib():
    return int(open("/proc/self/statm").read().split()[1]) * page / 2**20
before = resident_mib()
block = torch.ones(64 * 2**20 // 4)  # 64 MiB, above glibc's largest default mmap threshold
del block
print(resident_mib() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_on_the_cpu_freed_tensors_stay_with_the_process_for_reuse():
    def kept_mib(*args: str) -> float:
        command = [sys.executable, "-c", FREE_A_LARGE_BLOCK, *args]
        run = subprocess.run(command, capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        return float(run.stdout)

    assert kept_mib("none") < 8  # glibc's default: unmapped at once
    assert kept_mib("cpu") > 56  # kept, so the next batch does not page-fault it in again


def test_unknown_task_lists_the_valid_ones():
    with pytest.raises(envs.UnknownTaskError) as err:
        envs.make("cartpole-juggle", seed=0)
    assert "cartpole-balance" in str(err.value) and "cheetah-run" in str(err.value)
    for task in envs.PAPER_TASKS:
        envs.parse_task(task)
        envs.check_task(task)


def test_the_faithful_options_default_to_the_reference_and_reach_the_command_line():
    from nasa.cli import parse_train

    c = TrainConfig()
    assert c.sample_without_replacement is True and c.env.time_limit == "terminal"
    assert c.eval_at_start is True  # the project's one addition: a step-0 evaluation
    assert c.agent.ensemble_every == 1  # the reference's current code: the ensemble at every update
    cmd, _, _ = parse_train(["--preset", "paper", "--no-sample-without-replacement", "--time-limit",
                             "bootstrap", "--no-eval-at-start", "--ensemble-every", "5"])
    assert not cmd.config.sample_without_replacement and cmd.config.env.time_limit == "bootstrap"
    assert not cmd.config.eval_at_start and cmd.config.agent.ensemble_every == 5
    cmd, _, _ = parse_train(["--preset", "paper"])
    assert cmd.config.sample_without_replacement and cmd.config.env.time_limit == "terminal"


def test_each_algorithm_and_preset_draws_and_ends_episodes_as_its_own_reference_or_results():
    """NaSA-TD3's reference cuts the return at the time limit and draws without replacement;
    SAC-AE's bootstraps and draws with replacement; cpu-small keeps what its results were made with."""
    ways = {}
    for algo in ("nasa_td3", "td3_ae", "pixel_td3", "sac_ae"):
        for preset in ("paper", "cpu-small"):
            c = default_config(algo, preset)
            ways[algo, preset] = (c.env.time_limit, c.sample_without_replacement)
            validate(c)
    assert ways.pop(("nasa_td3", "paper")) == ways.pop(("td3_ae", "paper")) == ("terminal", True)
    assert ways.pop(("pixel_td3", "paper")) == ("terminal", True)
    assert set(ways.values()) == {("bootstrap", False)}  # sac_ae anywhere, and every cpu-small run


def test_service_defaults_are_shared_configs(monkeypatch):
    from shared import service
    from shared.zenoh_session import ServiceArgs

    args, preset = service.parse_with_preset(ServiceArgs, ["--preset", "paper"], "svc")
    assert preset == "paper" and args.config == default_config(TrainConfig().algo, "paper")
    # The pre-parser has no copy of its own: a changed default in shared.config is what it uses.
    monkeypatch.setattr(TrainConfig, "__init__", _with_default_algo(TrainConfig.__init__, "sac_ae"))
    args, _ = service.parse_with_preset(ServiceArgs, ["--preset", "paper"], "svc")
    assert args.config.agent == agent_defaults("sac_ae")


def _with_default_algo(init, algo):  # noqa: ANN001, ANN202
    def patched(self, *args, **kwargs):  # noqa: ANN001, ANN202
        kwargs.setdefault("algo", algo)
        init(self, *args, **kwargs)

    return patched


def test_frame_stack_starts_with_the_first_frame_repeated_and_shifts():
    env = envs.make("cartpole-balance", seed=0, render_quality="fast", image_size=32)
    ts = env.reset()
    assert ts.obs.shape == (9, 32, 32) and ts.obs.dtype == np.uint8 and ts.first
    for i in range(3):
        np.testing.assert_array_equal(ts.obs[3 * i : 3 * i + 3], ts.frame)
    nxt = env.step(np.zeros(env.action_dim))
    np.testing.assert_array_equal(nxt.obs[:3], ts.frame)
    np.testing.assert_array_equal(nxt.obs[6:], nxt.frame)
    with pytest.raises(ValueError, match="action shape"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.nan]))


def test_time_limit_ending_bootstraps_by_default_and_is_terminal_in_reference_mode():
    env = envs.make("cartpole-balance", seed=0, render_quality="fast", image_size=16, action_repeat=50)
    ts = env.reset()
    while not ts.last:
        ts = env.step(np.zeros(1))
    assert ts.discount == 1.0  # the suite's time limit
    assert envs.stored_discount(ts, "bootstrap") == 1.0
    assert envs.stored_discount(ts, "terminal") == 0.0


def test_action_repeat_sums_rewards():
    one = envs.make("cartpole-balance", seed=3, render_quality="fast", image_size=16)
    four = envs.make("cartpole-balance", seed=3, render_quality="fast", image_size=16, action_repeat=4)
    one.reset(), four.reset()
    total = sum(one.step(np.zeros(1)).reward for _ in range(4))
    assert four.step(np.zeros(1)).reward == pytest.approx(total)


def test_render_qualities_differ_but_show_the_same_scene():
    frames = {q: envs.make("cartpole-balance", seed=0, render_quality=q).reset().frame.astype(int)
              for q in ("paper", "fast", "plain")}
    for other in ("fast", "plain"):
        assert 0 < np.abs(frames["paper"] - frames[other]).mean() < 20
    assert 0 < np.abs(frames["fast"] - frames["plain"]).mean() < 20


def test_plain_quality_draws_no_shadows_or_reflections():
    env = envs.DMCPixels("ball_in_cup-catch", 0, 32, 0, 1, "plain")
    model = env._env.physics.model
    assert not model.light_castshadow.any() and not model.mat_reflectance.any()
    assert (model.vis.quality.shadowsize, model.vis.quality.offsamples) == (512, 0)
    paper = envs.DMCPixels("ball_in_cup-catch", 0, 32, 0, 1, "paper")._env.physics.model
    assert paper.light_castshadow.any() and paper.mat_reflectance.any()  # what plain turned off
    with pytest.raises(ValueError, match="render_quality must be one of paper, fast, plain"):
        envs.DMCPixels("ball_in_cup-catch", 0, 32, 0, 1, "nice")  # type: ignore[arg-type]


def test_env_rng_state_round_trip_repeats_the_episode_start():
    env = envs.make("reacher-hard", seed=0, render_quality="fast", image_size=16)
    env.reset()
    state = env.rng_state()
    first = env.reset().frame
    env.set_rng_state(state)
    np.testing.assert_array_equal(env.reset().frame, first)


def test_a_flag_the_algorithm_does_not_read_is_named_once_on_stderr(capsys):
    from nasa.cli import parse_train

    parse_train(["--algo", "sac_ae", "--target-noise", "0.3", "--no-shared-encoder-pass", "--tau", "0.02"])
    err = capsys.readouterr().err
    assert "--target-noise does nothing under --algo sac_ae: only nasa_td3, td3_ae, pixel_td3 read it" in err
    assert "--no-shared-encoder-pass does nothing under --algo sac_ae" in err
    assert "--tau" not in err and err.count("\n") == 2  # tau applies to every algorithm
    parse_train(["--algo", "nasa_td3", "--target-noise", "0.3", "--ensemble-every", "5"])
    parse_train(["--algo", "pixel_td3", "--init-temperature=0.2"])
    assert capsys.readouterr().err == "nasa train: note: --init-temperature does nothing under --algo " \
        "pixel_td3: only sac_ae read it\n"



def test_every_agent_field_some_algorithm_ignores_is_listed_where_the_agents_read_it():
    """FIELD_ALGOS names an algorithm for a field exactly when that algorithm's agent classes read it."""
    import inspect
    import re

    from shared.agents import AGENTS
    from shared.config import FIELD_ALGOS

    for algo, cls in AGENTS.items():
        mine = [c for c in cls.__mro__ if c.__module__.startswith("shared.agents")]
        source = "".join(inspect.getsource(c) for c in mine)
        read = {name for name in FIELD_ALGOS if re.search(rf"\b{name}\b", source)}
        assert read == {name for name, algos in FIELD_ALGOS.items() if algo in algos}, algo
