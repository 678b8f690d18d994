"""Reading the deployment files as the tools do: deploy/.env, the compose file with its
variables substituted, and the Kubernetes manifests with their `$(VAR)` args expanded."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
COMPOSE = DEPLOY / "docker-compose.yml"
ENV_FILE = DEPLOY / ".env"
K8S = DEPLOY / "k8s"
ROLES = ("router", "replay", "learner", "evaluator", "actor")
CONFIG_FLAGS = ("--preset", "--task", "--algo", "--seed", "--steps")

# ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?message}, ${VAR?message}
_COMPOSE_VAR = re.compile(r"\$\{(\w+)(?:(:?[-?])([^}]*))?\}")


def load_env(path: Path = ENV_FILE) -> dict[str, str]:
    env = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, sep, value = line.partition("=")
            assert sep, f"{path}: not KEY=VALUE: {line!r}"
            env[key.strip()] = value.strip()
    return env


def compose_variables(text: str | None = None) -> set[str]:
    return {m.group(1) for m in _COMPOSE_VAR.finditer(text if text is not None else COMPOSE.read_text())}


def substitute(text: str, env: dict[str, str]) -> str:
    def one(m: re.Match) -> str:
        name, op, arg = m.group(1), m.group(2), m.group(3)
        value = env.get(name)
        empty = value is None or (value == "" and op is not None and op.startswith(":"))
        if op and op.endswith("?") and empty:
            raise KeyError(f"{name} must be set: {arg}")
        if op and op.endswith("-") and empty:
            return arg
        return value or ""

    return _COMPOSE_VAR.sub(one, text)


def load_compose(overrides: dict[str, str] | None = None) -> dict:
    """The compose file as compose sees it with deploy/.env (and `overrides`) in the environment."""
    env = {**load_env(), **(overrides or {})}
    return yaml.safe_load(substitute(COMPOSE.read_text(), env))


def load_k8s() -> list[dict]:
    docs = []
    for path in sorted(K8S.glob("*.yaml")):
        docs += [d for d in yaml.safe_load_all(path.read_text()) if d]
    return docs


def k8s_config_map(docs: list[dict]) -> dict[str, str]:
    maps = [d for d in docs if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "nasa-td3-config"]
    assert len(maps) == 1
    return maps[0]["data"]


def k8s_containers(docs: list[dict]) -> dict[str, dict]:
    """role -> its one container (with `$(VAR)` in command and args expanded from the ConfigMap)."""
    values = k8s_config_map(docs)
    out = {}
    for d in docs:
        if d["kind"] not in ("Deployment", "StatefulSet"):
            continue
        (container,) = d["spec"]["template"]["spec"]["containers"]
        expanded = {**container}
        known = {**values, **container_env(container)}
        for key in ("command", "args"):
            expanded[key] = [re.sub(r"\$\((\w+)\)", lambda m, known=known: known[m.group(1)], a)
                             for a in container.get(key, [])]
        out[d["metadata"]["name"]] = expanded
    return out


def container_env(container: dict) -> dict[str, str]:
    """A container's own variables as Kubernetes sets them: values, and a resource's figure
    (`resourceFieldRef`, divisor 1: whole cores, rounded up). Secrets are not read here."""
    out = {}
    for var in container.get("env", []):
        if "value" in var:
            out[var["name"]] = var["value"]
        elif ref := var.get("valueFrom", {}).get("resourceFieldRef"):
            kind, _, name = ref["resource"].partition(".")
            out[var["name"]] = str(math.ceil(cpu_cores(container["resources"][kind][name])))
    return out


def cpu_cores(quantity: str) -> float:
    """A CPU quantity in cores: "2" -> 2, "250m" -> 0.25."""
    quantity = str(quantity)
    return int(quantity[:-1]) / 1000 if quantity.endswith("m") else float(quantity)


def flag_values(argv: list[str]) -> dict[str, str]:
    """--flag value pairs of an argument list (every flag here takes one value)."""
    flags = [i for i, a in enumerate(argv) if a.startswith("--")]
    return {argv[i]: argv[i + 1] for i in flags}


def torch_version() -> str:
    """The version pyproject.toml pins torch to (the image installs that one)."""
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    (pin,) = [d for d in deps if re.match(r"torch\s*==", d)]
    return pin.split("==")[1].strip()
