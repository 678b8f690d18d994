"""deploy/: the compose file and its .env, read as compose reads them: the topology, defaults that
match `nasa up`'s and shared/config.py's, and commands that are real modules whose --help lists
every flag they are given. tests/test_docker.py runs the same files under a real Docker engine."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import pytest
from compose_spec import PyCompose
from deploy_files import (
    COMPOSE,
    CONFIG_FLAGS,
    REPO,
    ROLES,
    compose_variables,
    flag_values,
    load_compose,
    load_env,
)
from docker_harness import Unavailable, apt_install

from nasa.up import UpCommand, parse_up
from shared.config import EnvConfig, TrainConfig, auto_preset, default_config
from shared.zenoh_session import env_run_id

UP = UpCommand()


def test_compose_file_is_commented_yaml_for_both_compose_versions():
    text = COMPOSE.read_text()
    assert text.lstrip().startswith("#") and not text.lstrip("# \n").startswith("{")
    compose = load_compose()
    # docker-compose 1.29 rejects a top-level `name`; the project name comes from .env
    assert set(compose) <= {"services", "volumes", "networks"} | {k for k in compose if k.startswith("x-")}
    assert "version" not in compose


def test_compose_file_is_valid_for_the_compose_specification():
    # compose-spec (a strict parser of the Compose Specification, which Compose v2 implements);
    # YAML merge keys resolved first, as compose does
    compose = load_compose()
    assert PyCompose.from_json(json.dumps(compose)).service_names() == list(compose["services"])
    broken = load_compose()
    broken["services"]["actor"]["depends_on"]["replay"]["condition"] = "service_ready"
    with pytest.raises(ValueError, match="service_ready"):
        PyCompose.from_json(json.dumps(broken))


def test_docker_compose_1_29_accepts_the_file():
    # Decided here, not at collection: on a fresh machine it is installed as test_docker's is.
    if not shutil.which("docker-compose"):
        try:
            apt_install("docker-compose")
        except Unavailable as err:
            pytest.skip(f"docker-compose (1.29): {err}")
    env = {k: v for k, v in os.environ.items() if k not in load_env()}  # .env's defaults, not the shell's
    proc = subprocess.run(["docker-compose", "-f", str(COMPOSE), "config", "-q"], capture_output=True,
                          text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_compose_has_the_topology():
    services = load_compose()["services"]
    assert set(services) == {*ROLES, "learner-gpu", "robot_bridge", "actor-robot"}
    env = load_env()
    for name, svc in services.items():
        assert svc["image"] == env["IMAGE"]
        assert svc["build"]["dockerfile"] == "deploy/Dockerfile"
        assert (COMPOSE.parent / svc["build"]["context"] / svc["build"]["dockerfile"]).exists()
        role = name.removesuffix("-gpu").removesuffix("-robot")
        assert svc["command"][:3] == ["python", "-m", f"services.{role}"]
        assert svc["healthcheck"]["test"] == ["CMD", "python", "/opt/nasa/healthcheck.py", role]
        assert svc["environment"]["NASA_RUN_ID"] == env["NASA_RUN_ID"]  # the router's: its ACL's run
        if role != "router":
            assert svc["environment"]["NASA_ZENOH_CONNECT"] == "tcp/router:7447"
            # nothing starts before what it needs is healthy
            assert set(svc["depends_on"]) & {"router", "replay"}
            assert all(d["condition"] == "service_healthy" for d in svc["depends_on"].values())
    actor = services["actor"]
    # `--scale actor=N` needs no fixed name, host port or actor id on the actor service
    assert "container_name" not in actor and "ports" not in actor
    assert "NASA_ACTOR_ID" not in actor["environment"]
    assert actor["scale"] == int(env["ACTORS"])
    # the gpu profile swaps the learner for one that reserves a GPU and runs on it
    assert services["learner"]["profiles"] == ["cpu"] and services["learner-gpu"]["profiles"] == ["gpu"]
    assert env["COMPOSE_PROFILES"] == "cpu"
    (device,) = services["learner-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert device["driver"] == "nvidia" and device["capabilities"] == ["gpu"]
    assert flag_values(services["learner-gpu"]["command"])["--device"] == "cuda"
    # the robot profile: the bridge owns the host's servo bus and camera, its actor steps it
    bridge, robot_actor = services["robot_bridge"], services["actor-robot"]
    assert bridge["profiles"] == robot_actor["profiles"] == ["robot"]
    assert bridge["devices"] == [f"{env['SERIAL_DEVICE']}:{env['SERIAL_DEVICE']}",
                                 f"{env['CAMERA_DEVICE']}:{env['CAMERA_DEVICE']}"]
    config = flag_values(bridge["command"][3:])["--config"]
    assert f"{env['GRIPPER_CONFIG']}:{config}:ro" in bridge["volumes"]
    assert flag_values(bridge["command"][3:])["--bridge-id"] == env["BRIDGE_ID"] == bridge["environment"][
        "NASA_BRIDGE_ID"]
    assert flag_values(robot_actor["command"][3:])["--bridge"] == env["BRIDGE_ID"]
    assert "robot_bridge" in robot_actor["depends_on"] and "ports" not in bridge
    for name in ("replay", "learner", "learner-gpu", "evaluator"):  # the evaluator's media: the dashboard's
        assert "run-data:/data" in services[name]["volumes"]
        assert flag_values(services[name]["command"])["--data"] == "/data"


def test_every_service_gets_the_same_config_flags():
    services = load_compose()["services"]
    env = load_env()
    expected = {"--preset": env["PRESET"], "--task": env["TASK"], "--algo": env["ALGO"],
                "--seed": env["SEED"], "--steps": env["STEPS"]}
    for name, svc in services.items():
        flags = flag_values(svc["command"][3:])
        if name == "robot_bridge":  # it takes the task and seed only: it is no learner's client
            assert (flags["--task"], flags["--seed"]) == (env["TASK"], env["SEED"])
        elif name != "router":
            assert {f: flags[f] for f in CONFIG_FLAGS} == expected, name


def test_ports_are_published_on_the_configured_address_only():
    services = load_compose({"PUBLISH_ADDRESS": "10.1.2.3", "ROUTER_PORT": "17447", "STATUS_PORT": "18000"})[
        "services"]
    assert services["router"]["ports"] == ["10.1.2.3:17447:7447"]
    assert services["learner"]["ports"] == ["10.1.2.3:18000:8000"]
    assert [n for n, s in services.items() if "ports" in s] == ["router", "learner", "learner-gpu"]
    assert load_env()["PUBLISH_ADDRESS"] == "127.0.0.1"  # no authentication: this host only by default


def test_env_file_holds_every_setting_and_nothing_else():
    env = load_env()
    used = compose_variables()
    assert used - set(env) == set(), "compose uses variables .env does not define"
    compose_own = {"COMPOSE_PROJECT_NAME", "COMPOSE_PROFILES"}
    assert set(env) - used - compose_own == set(), ".env sets variables compose does not use"
    # every variable must be set (${VAR:?}) but those whose empty value means something: TORCH_INDEX
    # (the variant's own index), NASA_ZENOH_AUTH (no Zenoh logins), NASA_API_TOKEN (open controls),
    # NASA_ZENOH_JOIN (no other site's router)
    for name in used - {"TORCH_INDEX", "NASA_ZENOH_AUTH", "NASA_API_TOKEN", "NASA_ZENOH_JOIN"}:
        assert re.search(rf"\$\{{{name}:\?", COMPOSE.read_text()), f"{name} has a default outside .env"


def test_env_defaults_match_nasa_up_and_config(monkeypatch):
    env = load_env()
    monkeypatch.delenv("NASA_RUN_ID", raising=False)
    train, env_config = TrainConfig(), EnvConfig()
    up, preset = parse_up([])  # nasa up with no flags, as the README's command 1
    assert env["TASK"] == up.config.env.task == env_config.task
    assert env["ALGO"] == up.config.algo == train.algo
    assert int(env["SEED"]) == up.config.seed == train.seed
    assert env["DEVICE"] == up.config.device == train.device
    # nasa up chooses actors and threads from the machine (0); compose names a fixed count
    assert UP.actors == 0 and int(env["ACTORS"]) >= 1
    assert int(env["ROUTER_PORT"]) == UP.router_port
    assert int(env["STATUS_PORT"]) == UP.port
    assert int(env["LEARNER_THREADS"]) == UP.learner_threads
    assert env["NASA_RUN_ID"] == env_run_id()
    # nasa up's `auto` resolves once per run; compose names what it resolves to on a CPU host,
    # and that preset's step budget (nasa up's steps with no flag)
    assert env["PRESET"] == auto_preset("cpu") == preset
    assert int(env["STEPS"]) == default_config(env["ALGO"], env["PRESET"]).steps == up.config.steps


def test_every_command_is_a_module_with_working_help():
    services = load_compose()["services"]
    procs = {}
    for name, svc in services.items():
        module = svc["command"][2]
        assert (REPO / "services" / module.split(".")[1] / "__main__.py").exists()
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", module, "--preset", "cpu-small", "--help"], cwd=REPO,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=120)
        assert proc.returncode == 0, f"{name}: {out}"
        for flag in (a for a in services[name]["command"][3:] if a.startswith("--")):
            assert re.search(rf"{re.escape(flag)}\b", out), f"{name} --help does not list {flag}"
