"""The runtime dependencies declared in pyproject.toml cover what the installed code imports."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RUNTIME_PACKAGES = ("nasa", "services", "shared")
FIRST_PARTY = {"nasa", "services", "shared", "bench", "tests"}


def declared(group: list[str]) -> set[str]:
    return {normalise(re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0]) for req in group}


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def imported_modules(folder: Path) -> dict[str, Path]:
    """Top-level module -> one file importing it, for every import in `folder` (at any depth)."""
    found: dict[str, Path] = {}
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], path)
    return found


def test_every_third_party_import_of_the_runtime_code_is_a_runtime_dependency():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = declared(project["dependencies"])
    dists = packages_distributions()
    missing = []
    for package in RUNTIME_PACKAGES:
        for module, where in imported_modules(REPO / package).items():
            if module in sys.stdlib_module_names or module in FIRST_PARTY or module == "__future__":
                continue
            owners = {normalise(d) for d in dists.get(module, [])}
            assert owners, f"{module} (imported by {where.relative_to(REPO)}) is not installed"
            if not owners & runtime:
                owner = ", ".join(sorted(owners))
                missing.append(f"{module} ({owner}), imported by {where.relative_to(REPO)}")
    assert missing == [], "imported at run time but not in [project].dependencies: " + "; ".join(missing)


def test_nasa_status_needs_httpx_at_run_time():
    # `nasa status` imports httpx: a dev-only dependency left it broken in the container image.
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert "httpx" in declared(project["dependencies"])
    assert "httpx" in imported_modules(REPO / "nasa")
