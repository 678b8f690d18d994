"""`nasa train --resume` and `nasa up` read their flags properly and refuse settings that differ
from the run's before anything starts (in process: no service, no training)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import nasa.train
from nasa import cli
from nasa.up import UpCommand, layout_of, parse_up, prepare, service_argv
from shared.config import ConfigError, TrainConfig, default_config, to_dict


@pytest.fixture
def resumed(tmp_path, monkeypatch) -> tuple[Path, list[int | None]]:
    """A run folder as `nasa train` leaves it, and Trainer.resume replaced by a recorder."""
    out = tmp_path / "run"
    out.mkdir()
    config = default_config("sac_ae", "cpu-small")
    config.steps, config.device = 3000, "cpu"
    (out / "config.json").write_text(json.dumps(to_dict(config), indent=2) + "\n")
    calls: list[int | None] = []

    class Recorded:
        def run(self) -> None:
            pass

    def resume(folder, steps=None, cuda_graph=None):  # noqa: ANN001, ANN202
        assert Path(folder) == out and cuda_graph is False  # the run's own setting, passed on
        calls.append(steps)
        return Recorded()

    monkeypatch.setattr(nasa.train.Trainer, "resume", staticmethod(resume))
    return out, calls


@pytest.mark.parametrize("flags", [["--steps=5000"], ["--steps", "5000"]])
def test_resume_takes_a_new_step_budget_however_it_is_written(resumed, flags):
    out, calls = resumed
    cli.main(["train", "--resume", str(out), *flags])
    assert calls == [5000]


def test_resume_without_flags_keeps_the_run_settings(resumed):
    out, calls = resumed
    cli.main(["train", "--resume", str(out)])  # no --algo sac_ae, no --preset: the run's
    cli.main(["train", "--resume", str(out), "--algo", "sac_ae", "--latent-dim", "50", "--steps", "3000"])
    assert calls == [None, None]


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--latent-dim", "7"], "agent.latent_dim (7 here, 50 in the run)"),
        (["--algo", "nasa_td3", "--steps=9000"], "algo ('nasa_td3' here, 'sac_ae' in the run)"),
        (["--device", "auto"], "device ('auto' here, 'cpu' in the run)"),
    ],
)
def test_resume_refuses_other_settings_naming_them(resumed, capsys, flags, named):
    out, calls = resumed
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--resume", str(out), *flags])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("nasa train: error: settings differ from the run's") and named in err
    assert calls == []


@pytest.mark.parametrize(("flags", "named"), [
    (["--out", "elsewhere"], "with --out elsewhere: a resumed run goes on in its own folder"),
    (["--preset", "paper"], "with --preset: a resumed run keeps the settings in its config.json"),
    (["--preset=cpu-small"], "with --preset: a resumed run keeps the settings in its config.json"),
])
def test_resume_refuses_an_out_or_preset_it_would_ignore(resumed, capsys, flags, named):
    out, calls = resumed
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--resume", str(out), *flags])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"nasa train: error: --resume {out} {named}" in err
    assert calls == []
    cli.main(["train", "--resume", str(out), "--out", str(out)])  # its own folder: no contradiction
    assert calls == [None]


@pytest.mark.filterwarnings("error")  # tyro's warning of a default of another type is a second line
@pytest.mark.parametrize(("field", "value"), [("steps", "300"), ("seed", None), ("batch_size", 64.5)])
def test_a_wrongly_typed_config_json_is_one_line_naming_the_field(resumed, capsys, field, value):
    from shared.service import parse_with_preset
    from shared.zenoh_session import ServiceArgs

    out, calls = resumed
    body = json.loads((out / "config.json").read_text())
    body[field] = value
    (out / "config.json").write_text(json.dumps(body))
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--resume", str(out)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith(f"nasa train: error: {field} must be a whole number")
    assert len(err.strip().splitlines()) == 1 and calls == []
    with pytest.raises(ConfigError, match=f"{field} must be a whole number"):  # a service's --run-config
        parse_with_preset(ServiceArgs, ["--run-config", str(out / "config.json")], "svc")


def test_resume_of_a_folder_without_a_run_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--resume", str(tmp_path / "none")])
    assert exit_.value.code == 2 and "no run there" in capsys.readouterr().err


def test_cuda_graph_on_a_cpu_is_refused_before_a_run_folder_is_made(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--cuda-graph", "--device", "cpu", "--out", str(tmp_path / "run")])
    assert exit_.value.code == 2 and "agent.cuda_graph needs a CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_cuda_graph_asked_for_on_resuming_is_applied_or_refused_not_ignored(tmp_path, capsys):
    import json

    from nasa.train import Trainer
    from tests.tiny import tiny_config

    run = tmp_path / "run"
    Trainer.create(tiny_config(steps=20), run)  # a run folder: config.json, no checkpoint yet
    before = (run / "config.json").read_text()
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--resume", str(run), "--cuda-graph"])
    assert exit_.value.code == 2 and "agent.cuda_graph needs a CUDA device" in capsys.readouterr().err
    assert (run / "config.json").read_text() == before
    trainer = Trainer.resume(run, cuda_graph=False)  # as asked: written to the run's settings
    assert not trainer.config.agent.cuda_graph
    assert json.loads((run / "config.json").read_text())["agent"]["cuda_graph"] is False


def test_nasa_up_declares_no_config_field_of_its_own():
    launcher = {f.name for f in dataclasses.fields(UpCommand)}
    assert not launcher & {f.name for f in dataclasses.fields(TrainConfig)}
    cmd, preset = parse_up(["--preset", "cpu-small", "--task", "reacher-hard", "--seed", "4", "--steps", "77",
                            "--actors", "3", "--", "--latent-dim", "12"])
    expected = default_config("nasa_td3", "cpu-small")
    expected.env.task, expected.seed, expected.steps, expected.agent.latent_dim = "reacher-hard", 4, 77, 12
    assert preset == "cpu-small" and cmd.config == expected and cmd.actors == 3


def test_every_service_of_nasa_up_gets_the_run_config(tmp_path):
    cmd, _ = parse_up(["--preset", "cpu-small", "--actors", "2", "--port", "9", "--learner-threads", "1"])
    argv = service_argv(cmd, tmp_path, layout_of(cmd, gpu=False))
    assert sorted(argv) == ["actor-0", "actor-1", "evaluator", "learner", "replay"]
    for args in argv.values():
        assert args[:2] == ["--run-config", str(tmp_path / "config.json")]
    assert argv["learner"][2:] == ["--data", str(tmp_path), "--port", "9", "--threads", "1",
                                   "--publish-every", "1"]
    # nasa up has checked the camera: the replay does not load the task's model again at each start
    assert argv["replay"][2:5] == ["--data", str(tmp_path), "--camera-checked"]
    cmd.evaluator = False
    assert "evaluator" not in service_argv(cmd, tmp_path, layout_of(cmd, gpu=False))


def test_nasa_up_passes_publish_every_to_the_learner_and_refuses_a_negative_one(tmp_path):
    def learner_flag(argv: list[str], gpu: bool) -> str | None:
        cmd, _ = parse_up(argv)
        learner = service_argv(cmd, tmp_path, layout_of(cmd, gpu=gpu))["learner"]
        return learner[learner.index("--publish-every") + 1] if "--publish-every" in learner else None

    assert learner_flag(["--preset", "cpu-small", "--publish-every", "7"], gpu=False) == "7"
    assert learner_flag(["--publish-every", "7"], gpu=True) == "7"
    # Chosen from the machine: every update on a CPU, the learner's own default with a GPU.
    assert learner_flag(["--preset", "cpu-small"], gpu=False) == "1"
    assert learner_flag([], gpu=True) is None
    with pytest.raises(ConfigError, match="publish-every"):
        parse_up(["--publish-every", "-1"])


def test_nasa_up_passes_the_actor_lead_to_the_replay_and_the_actors(tmp_path):
    def flags(argv: list[str], gpu: bool) -> tuple[list[str], list[str]]:
        cmd, _ = parse_up(["--preset", "cpu-small", *argv])
        out = service_argv(cmd, tmp_path, layout_of(cmd, gpu=gpu, cores=2))
        # after the run config and --data --camera-checked / --actor-id
        return out["replay"][5:], out["actor-0"][4:]

    assert flags([], gpu=False) == (["--error-buffer", "1"], ["--send-batch", "1", "--max-in-flight", "1"])
    assert flags(["--updates-per-step", "3"], gpu=False)[0] == ["--error-buffer", "3"]
    assert flags(["--actor-lead", "16"], gpu=True) == (
        ["--error-buffer", "16"], ["--send-batch", "8", "--max-in-flight", "2"])
    assert flags([], gpu=True) == ([], [])
    with pytest.raises(ConfigError, match="--actor-lead must be >= 0"):
        parse_up(["--actor-lead", "-2"])


def up_in_process(argv: list[str], capsys) -> tuple[int, str]:  # noqa: ANN001
    with pytest.raises(SystemExit) as exit_:
        cli.main(["up", "--router-port", "0", *argv])
    return exit_.value.code, capsys.readouterr().err


def test_nasa_up_refuses_a_resumed_folder_started_with_other_flags(tmp_path, capsys, monkeypatch):
    data = tmp_path / "run"
    cmd, _ = parse_up(["--preset", "cpu-small", "--image-size", "32", "--data", str(data)])
    prepare(cmd, data)  # the first `nasa up` wrote its config
    before = (data / "config.json").read_bytes()
    started = []
    monkeypatch.setattr("nasa.up.Supervisor.add", lambda *a, **k: started.append(a))
    code, err = up_in_process(["--preset", "cpu-small", "--image-size", "48", "--batch-size", "16",
                               "--data", str(data)], capsys)
    assert code == 2
    assert "nasa up: error: settings differ from the run's" in err
    assert "batch_size (16 here, 64 in the run), env.image_size (48 here, 32 in the run)" in err
    assert "start it with the run's settings (--batch-size 64 --image-size 32)" in err
    assert started == [] and sorted(p.name for p in data.iterdir() if p.name != ".lock") == ["config.json"]
    assert (data / "config.json").read_bytes() == before


@pytest.mark.parametrize("field", ["warmup_burst", "updates_before_store"])
def test_an_older_sac_ae_run_relaunched_is_refused_naming_the_flag_that_restores_its_settings(
        tmp_path, capsys, monkeypatch, field):
    """A SAC-AE run begun before --warmup-burst (or --updates-before-store) existed (its config.json
    lacks the field: off) is refused at its relaunch with its own command, as --algo sac_ae now has
    it on by default; the refusal names the flag that gives the run's setting back, and with it the
    run goes on."""
    data = tmp_path / "run"
    argv = ["--algo", "sac_ae", "--preset", "cpu-small", "--image-size", "32", "--data", str(data)]
    cmd, _ = parse_up(argv)
    prepare(cmd, data)
    body = json.loads((data / "config.json").read_text())
    del body[field]  # as a version before the field wrote it
    (data / "config.json").write_text(json.dumps(body))
    started = []
    monkeypatch.setattr("nasa.up.Supervisor.add", lambda *a, **k: started.append(a))
    code, err = up_in_process(argv, capsys)
    assert code == 2 and f"{field} (True here, False in the run)" in err and started == []
    flag = "--no-" + field.replace("_", "-")
    assert f"start it with the run's settings ({flag})" in err, err
    cmd, _ = parse_up([*argv, flag])
    assert getattr(prepare(cmd, data).config, field) is False


def test_nasa_up_rejects_an_unknown_task_before_writing_anything(tmp_path, capsys):
    code, err = up_in_process(["--task", "cartpole-juggle", "--data", str(tmp_path / "run")], capsys)
    assert code == 2 and "unknown task 'cartpole-juggle'; valid tasks are" in err
    assert not (tmp_path / "run").exists()


def test_nasa_help_lists_every_command_with_what_it_does(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        line = next(x for x in out.splitlines() if x.strip().startswith(name + " "))
        assert len(line.split()) > 3, line  # the name and a sentence
    with pytest.raises(SystemExit) as done:
        cli.main(["trian"])
    err = capsys.readouterr().err
    assert done.value.code == 2 and "unknown command 'trian'" in err and "commands:" in err


def test_python_dash_m_nasa_is_the_nasa_command() -> None:
    run = subprocess.run([sys.executable, "-m", "nasa", "--help"], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0 and "usage: nasa {up, train," in run.stdout


def test_nasa_train_rejects_an_unknown_task_before_announcing_the_run(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--task", "cartpole-juggle", "--out", str(tmp_path / "run")])
    out, err = capsys.readouterr()
    assert exit_.value.code == 2 and "unknown task 'cartpole-juggle'; valid tasks are" in err
    assert "cartpole-juggle" not in out  # no "nasa train: nasa_td3 on cartpole-juggle ..." line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("content", [b"", b"\x80\x02garbage", b"not a checkpoint" * 64])
def test_a_file_that_is_not_a_checkpoint_is_named_in_one_line(tmp_path, content):
    from shared.checkpoint import CheckpointError, load

    path = tmp_path / "checkpoint.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError) as err:
        load(path)
    message = str(err.value)
    assert message.startswith(f"{path} is not a readable checkpoint: ") and "\n" not in message
    assert "weights_only" not in message  # torch's advice to unpickle anything is not ours to give


def test_nasa_up_refuses_more_actors_than_the_host_can_hold(tmp_path, capsys, monkeypatch):
    from nasa import layout

    monkeypatch.setattr(layout, "usable_cores", lambda: 2)
    started = []
    monkeypatch.setattr("nasa.up.Supervisor.add", lambda *a, **k: started.append(a))
    code, err = up_in_process(["--actors", "500", "--data", str(tmp_path / "run")], capsys)
    assert code == 2 and "--actors 500 on 2 core(s): at most 16 on this host" in err
    assert started == [] and not (tmp_path / "run").exists()


@pytest.mark.parametrize(("flag", "value"), [("--port", "99999"), ("--port", "-1"), ("--port", "0"),
                                             ("--router-port", "65536")])
def test_nasa_up_refuses_a_port_that_is_not_one(tmp_path, capsys, flag, value):
    code, err = up_in_process([flag, value, "--data", str(tmp_path / "run")], capsys)
    assert code == 2 and f"{flag} must be a TCP port" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("run_id", ["a/b", "", "run*"])
def test_nasa_up_refuses_a_run_id_that_cannot_be_a_key_prefix_before_making_the_folder(
        tmp_path, capsys, monkeypatch, run_id):
    monkeypatch.setattr("nasa.up.Supervisor.add", lambda *a, **k: pytest.fail("a service was started"))
    code, err = up_in_process(["--run-id", run_id, "--data", str(tmp_path / "run")], capsys)
    assert code == 2 and "nasa up: error: --run-id: run id" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", [["train", "--device", "cpu", "--out"],
                                     ["up", "--router-port", "0", "--data"]])
@pytest.mark.parametrize(("task", "camera"), [("cartpole-balance", "99"), ("gripper-valve", "7")])
def test_a_camera_the_tasks_model_lacks_is_refused_before_the_run_folder_is_made(
        tmp_path, capsys, monkeypatch, command, task, camera):
    monkeypatch.setattr("nasa.up.Supervisor.add", lambda *a, **k: pytest.fail("a service was started"))
    with pytest.raises(SystemExit) as exit_:
        cli.main([*command, str(tmp_path / "run"), "--task", task, "--camera-id", camera])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"env.camera_id {camera} is not a camera of {task}: its model has" in err
    assert not (tmp_path / "run").exists()


def test_the_camera_check_takes_every_camera_of_the_model():
    from shared.config import EnvConfig
    from shared.envs import _load_suite_task, check_camera

    count = _load_suite_task("cartpole-balance", 0).physics.model.ncam
    check_camera(EnvConfig(task="cartpole-balance", camera_id=count - 1))
    with pytest.raises(ConfigError, match=f"has {count} \\(ids 0 to {count - 1}\\)"):
        check_camera(EnvConfig(task="cartpole-balance", camera_id=count))


@pytest.mark.parametrize("url", ["http://[::1", "http://127.0.0.1:abc/", "http://127.0.0.1:99999",
                                 "localhost:8000", "ftp://127.0.0.1:8000/"])
def test_nasa_status_refuses_what_is_not_an_address_in_one_line(tmp_path, capsys, url):
    with pytest.raises(SystemExit) as exc:
        cli.main(["status", "--url", url, "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"nasa status: error: --url {url!r} is not an address" in err
    assert "Traceback" not in err


def test_nasa_train_under_a_launcher_that_is_gone_does_not_start(tmp_path):
    """`nasa reproduce` names itself in NASA_PARENT_PID: a run whose launcher is not its parent (it
    died before the run asked for SIGTERM on its death) ends at once instead of running on its own."""
    env = {**os.environ, "NASA_PARENT_PID": "1"}  # not this run's parent
    done = subprocess.run([sys.executable, "-m", "nasa.cli", "train", "--task", "cartpole-nope", "--out",
                           str(tmp_path / "run")], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 1 and "unknown task" not in done.stderr  # it stopped before reading its flags
    assert done.stderr == ("not started: its launcher (pid 1, NASA_PARENT_PID) is not its parent process: "
                           "it has exited, or another program started this one\n")


@pytest.mark.parametrize(("parent", "says"), [
    ("1", "its launcher (pid 1, NASA_PARENT_PID) is not its parent process"),
    ("not-a-pid", "NASA_PARENT_PID='not-a-pid' names no process"),
])
def test_nasa_up_under_a_launcher_that_is_not_its_parent_says_so_and_does_not_start(tmp_path, parent, says):
    """It used to exit 1 silently (or with a ValueError's traceback for a value that is no pid)."""
    env = {**os.environ, "NASA_PARENT_PID": parent}
    done = subprocess.run([sys.executable, "-m", "nasa.cli", "up", "--task", "cartpole-nope", "--data",
                           str(tmp_path / "run")], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 1 and done.stderr.startswith(f"not started: {says}"), done.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("argv", "says"), [
    (["train", "--stepz", "3"], "Unrecognized options: --stepz, 3; did you mean --steps?"),
    (["train", "--steps", "x"], "Error parsing --steps: invalid literal for int()"),
    (["train", "--resume"], "argument --resume: expected one argument"),
    (["up", "--actorz", "1"], "Unrecognized options: --actorz, 1; did you mean --actors?"),
    (["up", "--bridge", "foo"], "invalid choice 'foo' for argument '--bridge'. Expected one of ('off',"),
    (["up", "--preset"], "argument --preset: expected one argument"),
    (["plot", "DIR", "--bogus"], "Unrecognized options: --bogus"),
    (["auth", "init", "DIR", "--forse"], "Unrecognized options: --forse; did you mean --force?"),
    (["auth", "tls", "DIR", "--hots", "h"], "Unrecognized options: --hots, h; did you mean --host?"),
    (["status", "--prot", "1"], "Unrecognized options: --prot, 1; did you mean --port?"),
    (["reproduce", "--seeds", "x"], "Error parsing --seeds"),
])
def test_a_flag_a_command_refuses_is_one_line_naming_it_and_exit_2(tmp_path, capsys, argv, says):
    argv = [str(tmp_path / "dir") if a == "DIR" else a for a in argv]
    with pytest.raises(SystemExit) as done:
        cli.main(argv)
    out, err = capsys.readouterr()
    assert done.value.code == 2 and not out, err
    assert err.startswith(f"nasa {argv[0]}: error: {says}") and err.count("\n") == 1, err
    prog = " ".join(argv[:2] if argv[0] == "auth" else argv[:1])
    assert err.endswith(f"(`nasa {prog} --help` lists its flags)\n"), err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [["train"], ["up"], ["plot"], ["auth", "init"], ["auth", "tls"],
                                  ["status"], ["reproduce"], ["reproduce", "--"]])
def test_help_is_the_parsers_own_on_stdout(capsys, argv):
    # After `nasa reproduce --`, the flags are nasa train's: so is its help.
    with pytest.raises(SystemExit) as done:
        cli.main([*argv, "--help"])
    out, err = capsys.readouterr()
    prog = "train" if argv[-1] == "--" else " ".join(argv)
    assert done.value.code == 0 and not err, err
    assert out.startswith(f"usage: nasa {prog} [-h]") and "--help" in out, out


def test_nasa_auth_names_an_unknown_command_and_prints_its_help_on_stdout(capsys) -> None:
    # As `nasa trian` and `nasa --help` do.
    with pytest.raises(SystemExit) as done:
        cli.main(["auth", "int", "DIR"])
    out, err = capsys.readouterr()
    assert done.value.code == 2 and not out
    assert err.startswith("nasa auth: unknown command 'int'\nusage: nasa auth init DIR"), err
    with pytest.raises(SystemExit) as done:
        cli.main(["auth", "--help"])
    out, err = capsys.readouterr()
    assert done.value.code == 0 and not err and out.startswith("usage: nasa auth init DIR"), out
