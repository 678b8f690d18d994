"""A Docker engine and compose for tests/test_docker.py: use the running engine, or start one
(installing Debian's docker.io / docker-compose as root when missing), and say why not when it
cannot; make the base image; put the local torch wheel and CA certificates where the build sees
them. Everything it starts or stages it undoes in `close()`."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from deploy_files import DEPLOY, REPO


class Unavailable(Exception):
    """What this machine lacks for the test (the test is skipped with it)."""


def run(argv: list[str], timeout: float = 600, env: dict | None = None, check: bool = True,
        ) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    if check and proc.returncode != 0:
        out = f"{proc.stdout[-3000:]}{proc.stderr[-3000:]}"
        raise RuntimeError(f"{' '.join(argv)} exited {proc.returncode}:\n{out}")
    return proc


def _ok(argv: list[str], timeout: float = 60) -> bool:
    try:
        return run(argv, timeout=timeout, check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def apt_install(*packages: str) -> None:
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        raise Unavailable(f"{', '.join(packages)} missing and not root with apt-get to install them")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for argv in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", *packages]):
        proc = run(argv, timeout=900, env=env, check=False)
        if proc.returncode != 0:
            raise Unavailable(f"apt-get could not install {packages}: {proc.stderr[-500:]}")


class DockerHost:
    """The engine, the compose command and the staged build inputs of one test run; a dockerd it
    starts logs to `dockerd.log` in `folder` (the run's own: two runs never share a log)."""

    def __init__(self, folder: Path) -> None:
        self.dockerd_log = folder / "dockerd.log"
        self.dockerd: subprocess.Popen | None = None
        self.staged: list[Path] = []
        self.compose: list[str] = []
        self.torch_index = ""

    def start(self) -> None:
        if not _ok(["docker", "info"]):
            self._start_dockerd()
        self.compose = self._compose_command()

    def _start_dockerd(self) -> None:
        if os.geteuid() != 0:
            raise Unavailable("no Docker engine answers `docker info` and starting one needs root")
        if not shutil.which("dockerd") or not shutil.which("docker"):
            apt_install("docker.io")
        self.dockerd_log.parent.mkdir(parents=True, exist_ok=True)
        with self.dockerd_log.open("wb") as log:
            self.dockerd = subprocess.Popen(["dockerd"], stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 120
        while not _ok(["docker", "info"], timeout=20):
            if self.dockerd.poll() is not None or time.monotonic() > deadline:
                self._stop_dockerd()
                tail = self.dockerd_log.read_text(errors="replace").strip().splitlines()[-3:]
                raise Unavailable(f"dockerd did not start here (log: {self.dockerd_log}): {' | '.join(tail)}")
            time.sleep(1)

    def _compose_command(self) -> list[str]:
        if _ok(["docker", "compose", "version"]):
            return ["docker", "compose"]
        if not shutil.which("docker-compose"):
            apt_install("docker-compose")
        if not _ok(["docker-compose", "version"]):
            raise Unavailable("neither `docker compose` nor `docker-compose` works here")
        return ["docker-compose"]

    def base_image(self) -> str:
        """Make the Dockerfile's FROM image when no registry gives it (debootstrap, as root)."""
        text = (DEPLOY / "Dockerfile").read_text()
        tag = re.search(r"^ARG BASE_IMAGE=(\S+)", text, re.M).group(1)
        if not _ok(["docker", "image", "inspect", tag]):
            if os.geteuid() != 0:
                raise Unavailable(f"no base image {tag}; making one with debootstrap needs root")
            run(["bash", "scripts/docker_base_image.sh", tag], timeout=1200)
        return tag

    def stage_build_inputs(self, torch_version: str) -> None:
        """A CPU torch wheel from pip's find-links (TORCH_INDEX=local then), and the host's own
        CA certificates, where the build sees them; both are removed in close()."""
        for directory in _find_links():
            wheels = sorted(Path(directory).glob(f"torch-{torch_version}+cpu-*.whl"))
            if wheels:
                self._stage(wheels[-1], DEPLOY / "wheels")
                self.torch_index = "local"
                break
        for cert in sorted(Path("/usr/local/share/ca-certificates").glob("*.crt")):
            self._stage(cert, DEPLOY / "ca-certificates")

    def _stage(self, source: Path, folder: Path) -> None:
        target = folder / source.name
        if target.exists():
            return
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)
        self.staged.append(target)

    def close(self) -> None:
        for path in self.staged:
            path.unlink(missing_ok=True)
        self._stop_dockerd()

    def _stop_dockerd(self) -> None:
        if self.dockerd is not None and self.dockerd.poll() is None:
            self.dockerd.terminate()
            try:
                self.dockerd.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.dockerd.kill()
                self.dockerd.wait()
        self.dockerd = None


def _find_links() -> list[str]:
    """The directories pip's configuration names as find-links (environment or config files)."""
    dirs = os.environ.get("PIP_FIND_LINKS", "").split()
    proc = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        key, _, value = line.partition("=")
        if key.endswith("find-links"):
            dirs += value.strip().strip("'\"").split()
    return [d for d in dict.fromkeys(dirs) if Path(d).is_dir()]
