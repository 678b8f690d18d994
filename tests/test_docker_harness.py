"""tests/docker_harness.py without a Docker engine: a dockerd that cannot start here (a stand-in
executable that fails as a real one does without the privileges it needs) is reported with the
log of its own run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from docker_harness import DockerHost, Unavailable


def stand_in(folder: Path, name: str, script: str) -> None:
    path = folder / name
    path.write_text(f"#!/bin/sh\n{script}\n")
    path.chmod(0o755)


@pytest.mark.skipif(os.geteuid() != 0, reason="the harness starts dockerd only as root")
def test_each_run_of_the_harness_logs_dockerd_in_its_own_folder_and_says_where(tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    stand_in(bin_dir, "docker", "exit 1")  # no engine answers `docker info`
    stand_in(bin_dir, "dockerd", 'echo "failed to start daemon: run $RUN"; exit 1')
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    for run in ("a", "b"):  # two runs at once on one machine, or two users
        monkeypatch.setenv("RUN", run)
        host = DockerHost(tmp_path / run)
        with pytest.raises(Unavailable) as failed:
            host.start()
        assert host.dockerd_log == tmp_path / run / "dockerd.log"
        assert f"(log: {host.dockerd_log}): failed to start daemon: run {run}" in str(failed.value)
    assert (tmp_path / "a" / "dockerd.log").read_text() == "failed to start daemon: run a\n"
