"""The run's resolved config: digest, differing fields, the run folder's config.json, and the
replay's config queryable over a real Zenoh session on loopback."""

from __future__ import annotations

import json
import threading

import pytest

from nasa.up import free_port
from shared import envs, run_config, wire
from shared.config import ConfigError, TrainConfig, default_config, to_dict
from shared.replay.log import StoreFormatError
from shared.run_config import ConfigMismatch, RunConfig
from shared.service import StopFlag, bad_input_errors, parse_with_preset
from shared.zenoh_session import ServiceArgs, open_client, open_router

SPEC = envs.EnvSpec((3, 32, 32), 3, 1)


def small(**changes) -> TrainConfig:
    config = default_config("nasa_td3", "cpu-small", "cartpole-balance")
    config.env.task = "cartpole-balance"  # SPEC's one action dimension
    config.env.image_size = 32
    for name, value in changes.items():
        *parents, leaf = name.split("__")
        target = config
        for p in parents:
            target = getattr(target, p)
        setattr(target, leaf, value)
    return config


def test_digest_is_of_the_shared_settings():
    a = RunConfig(small(), SPEC)
    assert len(a.digest()) == 16 and int(a.digest(), 16) >= 0
    assert RunConfig(small(), SPEC).digest() == a.digest()
    assert RunConfig(small(device="cuda"), SPEC).digest() == a.digest()  # each process's own
    assert RunConfig(small(agent__latent_dim=7), SPEC).digest() != a.digest()
    assert RunConfig(small(), envs.EnvSpec((3, 32, 32), 3, 2)).digest() != a.digest()


def test_to_dict_round_trips_and_keeps_the_config_at_the_top_level():
    run = RunConfig(small(sample_without_replacement=True, eval_at_start=False), SPEC)
    d = run.to_dict()
    assert d["env"]["task"] == "cartpole-balance" and d["algo"] == "nasa_td3" and d["spec"]["action_dim"] == 1
    back = RunConfig.from_dict(json.loads(json.dumps(d)))
    assert back == run and back.digest() == run.digest()
    with pytest.raises(ConfigError, match="no environment spec"):
        RunConfig.from_dict(to_dict(small()))
    with pytest.raises(ConfigError, match="not a config this version reads"):
        RunConfig.from_dict({**d, "learning_rate": 1})


def test_differing_fields_are_dotted_names_in_declaration_order():
    a, b = small(), small(steps=7, agent__latent_dim=3, env__frame_stack=2, device="cuda")
    assert run_config.differing_fields(a, b) == ["steps", "device", "env.frame_stack", "agent.latent_dim"]
    assert run_config.differing_fields(a, b, ignore=("device", "steps")) == [
        "env.frame_stack", "agent.latent_dim"]
    assert run_config.differing_fields(a, small()) == []


def test_a_mismatch_names_the_fields_and_is_a_bad_input_error():
    with pytest.raises(ConfigMismatch) as err:
        run_config.check_same(small(agent__latent_dim=3), small(), "here")
    assert err.value.fields == ["agent.latent_dim"]
    assert "agent.latent_dim (3 here, 50 in the run)" in str(err.value)
    assert "start it with the run's settings (--latent-dim 50)" in str(err.value)
    assert isinstance(err.value, bad_input_errors())
    run_config.check_same(small(device="cuda", steps=9), small(), "here", may_change=("steps",))


def test_a_replay_folder_of_another_config_is_a_bad_input_error(tmp_path):
    # It used to crash-loop: the replay exited 1 and nasa up restarted it again and again.
    from shared.replay.store import ReplayStore

    ReplayStore(capacity=16, frame_shape=(3, 8, 8), frame_stack=3, action_dim=1,
                data_dir=tmp_path, compression="lz4").close()
    with pytest.raises(StoreFormatError) as err:
        ReplayStore(capacity=16, frame_shape=(3, 8, 8), frame_stack=3, action_dim=1,
                    data_dir=tmp_path, compression="zstd")
    assert isinstance(err.value, bad_input_errors())


def test_open_folder_writes_the_resolved_config_once(tmp_path):
    data = tmp_path / "run"
    run = run_config.open_folder(small(), data)
    assert run.spec == SPEC
    saved = json.loads((data / "config.json").read_text())
    assert saved == run.to_dict()
    assert [p.name for p in data.iterdir()] == ["config.json"]  # no temporary file left
    again = run_config.open_folder(small(), data)
    assert again == run and (data / "config.json").read_text() == json.dumps(saved, indent=2) + "\n"


def test_open_folder_refuses_other_settings_and_leaves_the_file(tmp_path):
    data = tmp_path / "run"
    run_config.open_folder(small(), data)
    before = (data / "config.json").read_bytes()
    with pytest.raises(ConfigMismatch) as err:
        run_config.open_folder(small(env__image_size=48, batch_size=8), data)
    assert err.value.fields == ["batch_size", "env.image_size"]
    assert str(data / "config.json") in str(err.value)
    with pytest.raises(ConfigMismatch, match="steps"):
        run_config.open_folder(small(steps=123), data)  # steps only where the caller allows it
    assert (data / "config.json").read_bytes() == before


def test_a_resumed_run_may_change_its_step_budget(tmp_path):
    data = tmp_path / "run"
    run_config.open_folder(small(), data)
    run = run_config.open_folder(small(steps=123, device="cpu"), data, may_change=("steps",))
    assert run.config.steps == 123
    saved = run_config.read_config(data / "config.json")
    assert saved.steps == 123 and saved.device == "cpu"  # for the services started with --run-config


def test_a_config_json_without_a_spec_gets_one_and_a_broken_one_is_refused(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps(to_dict(small())))  # as `nasa train` writes it
    run = run_config.open_folder(small(), tmp_path)
    assert run.spec == SPEC and json.loads((tmp_path / "config.json").read_text())["spec"] == SPEC.to_dict()
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="unreadable"):
        run_config.open_folder(small(), tmp_path)


def test_a_service_started_with_the_run_config_takes_its_settings_and_refuses_others(tmp_path):
    run_config.open_folder(small(warmup_steps=33), tmp_path)
    path = str(tmp_path / "config.json")
    args, preset = parse_with_preset(ServiceArgs, ["--run-config", path], "svc")
    assert preset == "run" and args.config == small(warmup_steps=33)
    same, _ = parse_with_preset(ServiceArgs, ["--run-config", path, "--warmup-steps", "33"], "svc")
    assert same.config == args.config
    with pytest.raises(ConfigMismatch, match=r"warmup_steps \(34 here, 33 in the run\)"):
        parse_with_preset(ServiceArgs, ["--run-config", path, "--warmup-steps", "34"], "svc")



@pytest.mark.parametrize("preset", [["--preset", "paper"], ["--preset=cpu-small"]])
def test_a_service_given_a_preset_and_the_run_config_refuses_the_preset(tmp_path, preset):
    run_config.open_folder(small(), tmp_path)
    path = str(tmp_path / "config.json")
    with pytest.raises(ConfigError, match="with --run-config .*leave --preset out"):
        parse_with_preset(ServiceArgs, ["--run-config", path, *preset], "svc")


@pytest.fixture
def zenoh_pair():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_router(endpoint), open_client(endpoint) as replay, open_client(endpoint) as learner:
        yield replay, learner, wire.Keys(f"t{free_port()}")


def test_join_gets_the_run_config_from_the_replay(zenoh_pair):
    replay, learner, keys = zenoh_pair
    run = RunConfig(small(), SPEC)
    with run_config.serve(replay, keys, run):
        joined = run_config.join(small(device="cpu"), learner, keys, StopFlag(), timeout_s=5.0)
        assert joined is not None and joined.spec == SPEC
        assert joined.config.device == "cpu"  # the caller's own device
        with pytest.raises(ConfigMismatch, match="agent.latent_dim"):
            run_config.join(small(agent__latent_dim=3), learner, keys, StopFlag(), timeout_s=5.0)


def test_join_waits_for_the_replay_and_gives_up_when_stopped(zenoh_pair):
    replay, learner, keys = zenoh_pair
    stop = threading.Event()
    result: list = []
    worker = threading.Thread(target=lambda: result.append(
        run_config.join(small(), learner, keys, stop, timeout_s=0.5, retry_s=0.05)))
    worker.start()
    with run_config.serve(replay, keys, RunConfig(small(), SPEC)):  # the replay starts later
        worker.join(timeout=20)
    assert not worker.is_alive() and result[0].spec == SPEC
    stop.set()
    assert run_config.join(small(), learner, keys, stop, timeout_s=0.5) is None  # no replay, stopped


def test_a_replay_of_another_wire_version_is_a_bad_input_error(zenoh_pair):
    replay, learner, keys = zenoh_pair
    queryable = replay.declare_queryable(keys.config, lambda q: q.reply(keys.config, b"\x93\x01\x02\x03"))
    try:
        with pytest.raises(ConfigError, match="the replay's config is unreadable"):
            run_config.join(small(), learner, keys, StopFlag(), timeout_s=5.0)
    finally:
        queryable.undeclare()


def test_a_config_json_the_disk_cannot_hold_leaves_no_half_copy_and_the_old_one(tmp_path, monkeypatch):
    import builtins

    from shared import files
    from tests.test_train import FullFile

    run_config.write_folder(tmp_path, RunConfig(small(), SPEC))
    before = (tmp_path / run_config.CONFIG_FILE).read_bytes()
    # The temporary copy is made, then the disk refuses its text.
    monkeypatch.setattr(files, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
    with pytest.raises(OSError, match="No space left"):
        run_config.write_folder(tmp_path, RunConfig(small(steps=999), SPEC))
    assert sorted(p.name for p in tmp_path.iterdir()) == [run_config.CONFIG_FILE]
    assert (tmp_path / run_config.CONFIG_FILE).read_bytes() == before
