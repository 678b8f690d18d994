"""The image and the compose file under a real Docker engine: build, `up --scale actor=2`, the
status shows both actors alive and updates growing, scale to 3 live, stop, and the run folder on
the volume holds the checkpoint and the replay log. Prints how long build, up, scale and stop took.

Runs where a Docker engine runs or can be started (tests/docker_harness.py); skipped with the
reason elsewhere. The engine's cache (the base image, the build stage's layers with torch and the
pinned packages) is kept between runs, so only the first run builds from nothing."""

from __future__ import annotations

import json
import os
import time
import urllib.request
from collections.abc import Callable, Iterator

import pytest
from deploy_files import COMPOSE, torch_version
from docker_harness import DockerHost, Unavailable, run

from nasa.up import free_port

pytestmark = [pytest.mark.docker, pytest.mark.system, pytest.mark.timeout(3600)]

PROJECT = "nasa-td3-test"
IMAGE = "nasa-td3-test:latest"


@pytest.fixture(scope="module")
def host(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DockerHost]:
    docker = DockerHost(tmp_path_factory.mktemp("docker"))
    try:
        docker.start()
        docker.base_image()
    except Unavailable as why:
        docker.close()
        pytest.skip(f"no Docker engine for this test: {why}")
    if docker.dockerd is not None:
        print(f"dockerd started by the test, its log: {docker.dockerd_log}")  # shown if the test fails
    try:
        yield docker
    finally:
        docker.close()


class Compose:
    def __init__(self, host: DockerHost, env: dict[str, str]) -> None:
        self.argv = [*host.compose, "-f", str(COMPOSE), "-p", PROJECT]
        self.env = env

    def __call__(self, *args: str, timeout: float = 600, check: bool = True) -> str:
        return run([*self.argv, *args], timeout=timeout, env=self.env, check=check).stdout


def _status(port: int) -> dict | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=5) as response:
            return json.load(response)
    except (OSError, ValueError):
        return None


def _wait(what: str, check: Callable[[], bool], timeout_s: float, compose: Compose) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            logs = compose("logs", "--tail", "15", check=False)
            pytest.fail(f"{what} not within {timeout_s:.0f} s; logs:\n{logs[-6000:]}")
        time.sleep(3)


def _alive(status: dict | None) -> int:
    return sum(1 for a in (status or {}).get("actors", []) if a["alive"])


def _updates_growing(port: int, seen: list[int]) -> bool:
    status = _status(port)
    if status is None or _alive(status) < 2 or status["updates"] == 0:
        return False
    seen.append(status["updates"])
    return seen[-1] > seen[0]


def test_compose_builds_runs_scales_and_stops(host: DockerHost, capsys: pytest.CaptureFixture) -> None:
    host.stage_build_inputs(torch_version())
    port = free_port()
    env = {**os.environ, "IMAGE": IMAGE, "TORCH_INDEX": host.torch_index, "COMPOSE_PROJECT_NAME": PROJECT,
           "STATUS_PORT": str(port), "ROUTER_PORT": str(free_port()), "DOCKER_BUILDKIT": "0",
           "COMPOSE_DOCKER_CLI_BUILD": "0"}
    compose = Compose(host, env)
    compose("down", "--volumes", "--remove-orphans", check=False)  # what a failed run left
    times: dict[str, float] = {}
    try:
        t0 = time.monotonic()
        compose("build", "router", timeout=3000)  # every service runs this one image
        times["build"] = time.monotonic() - t0

        t0 = time.monotonic()
        compose("up", "-d", "--scale", "actor=2", timeout=900)
        seen: list[int] = []
        _wait("both actors alive and updates growing", lambda: _updates_growing(port, seen), 900, compose)
        times["up"] = time.monotonic() - t0
        _check_inside_the_learner(compose, port)

        t0 = time.monotonic()
        compose("up", "-d", "--no-recreate", "--scale", "actor=3", timeout=600)
        _wait("a third actor alive", lambda: _alive(_status(port)) >= 3, 600, compose)
        times["scale"] = time.monotonic() - t0

        t0 = time.monotonic()
        compose("stop", timeout=600)
        times["stop"] = time.monotonic() - t0
        _check_run_folder(compose)
    finally:
        compose("down", "--volumes", "--rmi", "all", "--remove-orphans", timeout=600, check=False)
        with capsys.disabled():
            print("\ndocker test timings: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items()))


def _check_inside_the_learner(compose: Compose, port: int) -> None:
    # the learner's own container: a non-root user, and `nasa status` works there
    assert compose("exec", "-T", "learner", "id", "-u").strip() == "1000"
    status = json.loads(compose("exec", "-T", "learner", "nasa", "status"))
    assert status["updates"] > 0 and status["task"] == "ball_in_cup-catch"
    # only one learner (the cpu profile's), and the actors have no fixed names
    assert compose("ps", "-q", "learner-gpu", check=False).strip() == ""
    assert _status(port) is not None


def _check_run_folder(compose: Compose) -> None:
    volumes = run(["docker", "volume", "ls", "-q", "--filter", f"label=com.docker.compose.project={PROJECT}"]
                  ).stdout.split()
    (volume,) = [v for v in volumes if v.endswith("run-data")]
    files = run(["docker", "run", "--rm", "-v", f"{volume}:/data", "--entrypoint", "find", IMAGE,
                 "/data", "-type", "f", "-size", "+0"]).stdout.split()
    assert "/data/learner/checkpoint.pt" in files, files
    assert "/data/replay/MANIFEST.json" in files, files
    assert any(f.startswith("/data/media/") for f in files), files  # the evaluator's, on the same volume
    assert any(f.startswith("/data/replay/") and f != "/data/replay/MANIFEST.json" for f in files), files
