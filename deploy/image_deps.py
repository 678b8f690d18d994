"""What deploy/Dockerfile installs, read from pyproject.toml so the pins have one home.

    python image_deps.py torch PYPROJECT          the torch requirement (e.g. torch==2.13.0)
    python image_deps.py requirements PYPROJECT   every other runtime requirement, one a line
    python image_deps.py default-index VARIANT    where torch comes from for cpu / cuda
    python image_deps.py check-torch VARIANT      exit 1 unless the installed torch is that variant

Runs with the standard library only: it runs in the image before anything is installed.
"""

from __future__ import annotations

import re
import sys
import tomllib

# The CPU index holds the CPU build; PyPI's default Linux torch is the CUDA build.
DEFAULT_INDEX = {"cpu": "https://download.pytorch.org/whl/cpu", "cuda": "https://pypi.org/simple"}


def _name(requirement: str) -> str:
    return re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].strip().lower()


def load(pyproject: str) -> tuple[list[str], list[str]]:
    with open(pyproject, "rb") as f:
        project = tomllib.load(f)["project"]
    dev = project.get("optional-dependencies", {}).get("dev", [])
    return list(project["dependencies"]), list(dev)


def torch_requirement(pyproject: str) -> str:
    deps, _ = load(pyproject)
    found = [d for d in deps if _name(d) == "torch"]
    if len(found) != 1:
        raise SystemExit(f"image_deps: expected one torch requirement in {pyproject}, found {found}")
    return found[0]


def requirements(pyproject: str) -> list[str]:
    """The runtime pins the image installs (torch apart: it comes from the variant's index)."""
    deps, _ = load(pyproject)
    # setuptools: the project itself is installed without build isolation.
    return [d for d in deps if _name(d) != "torch"] + ["setuptools>=68"]


def check_torch(variant: str) -> None:
    import torch

    cuda = torch.version.cuda
    if (variant == "cuda") != (cuda is not None):
        build = f"CUDA {cuda}" if cuda else "CPU"
        raise SystemExit(f"image_deps: asked for the {variant} variant but torch {torch.__version__} "
                         f"is a {build} build; set TORCH_INDEX to an index that has the {variant} build")
    print(f"image_deps: torch {torch.__version__} ({variant}) ok")


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        raise SystemExit(__doc__)
    command, arg = argv
    if command == "torch":
        print(torch_requirement(arg))
    elif command == "requirements":
        print("\n".join(requirements(arg)))
    elif command in ("default-index", "check-torch"):
        if arg not in DEFAULT_INDEX:
            raise SystemExit(f"image_deps: TORCH_VARIANT must be one of {sorted(DEFAULT_INDEX)}, got {arg!r}")
        if command == "default-index":
            print(DEFAULT_INDEX[arg])
        else:
            check_torch(arg)
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
