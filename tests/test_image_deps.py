"""deploy/image_deps.py, what the image build runs: the pins come from pyproject.toml, the runtime
extras are there, and the torch check refuses the wrong build (run here against this venv's torch)."""

from __future__ import annotations

import re
import subprocess
import sys

import torch
from deploy_files import DEPLOY, REPO, torch_version

SCRIPT = DEPLOY / "image_deps.py"
PYPROJECT = str(REPO / "pyproject.toml")


def image_deps(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=120)


def test_requirements_are_the_runtime_pins_without_torch():
    assert image_deps("torch", PYPROJECT).stdout.strip() == f"torch=={torch_version()}"
    lines = image_deps("requirements", PYPROJECT).stdout.split()
    assert not any(re.match(r"torch\b", line) for line in lines)
    assert "mujoco==3.17.0" in lines and "eclipse-zenoh==1.10.2" in lines
    assert "httpx==0.28.1" in lines  # `nasa status` needs it in the image


def test_torch_check_refuses_the_other_build():
    installed = "cuda" if torch.version.cuda else "cpu"
    other = "cpu" if installed == "cuda" else "cuda"
    ok = image_deps("check-torch", installed)
    assert ok.returncode == 0, ok.stderr
    wrong = image_deps("check-torch", other)
    assert wrong.returncode == 1
    assert f"asked for the {other} variant" in wrong.stderr and "TORCH_INDEX" in wrong.stderr
    assert image_deps("check-torch", "gpu").returncode == 1
    assert image_deps("default-index", "cpu").stdout.strip() == "https://download.pytorch.org/whl/cpu"


def test_dockerfile_checks_torch_after_every_install():
    text = (DEPLOY / "Dockerfile").read_text()
    installs = [m.start() for m in re.finditer(r"\bpip install\b", text)]
    checks = [m.start() for m in re.finditer(r"check-torch", text)]
    # every RUN that installs ends with the check, and the last install is followed by one
    runs = [r for r in text.split("\nRUN ") if "pip install" in r]
    assert runs and all("check-torch" in r for r in runs)
    assert checks and max(checks) > max(installs)
