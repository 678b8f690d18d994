"""deploy/: the compose file parses, has every service, and each command is a real module whose
--help works and lists every flag the command passes. (No Docker engine here: see DESIGN.md.)"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMPOSE = REPO / "deploy" / "docker-compose.yml"


def load_compose() -> dict:
    # The file is JSON-compatible YAML (PyYAML is not a dependency): drop the comment lines.
    text = "\n".join(line for line in COMPOSE.read_text().splitlines() if not line.lstrip().startswith("#"))
    return json.loads(text)


def test_compose_has_the_topology():
    compose = load_compose()
    services = compose["services"]
    assert set(services) == {"router", "replay", "learner", "evaluator", "actor"}
    actor = services["actor"]
    # `docker compose up --scale actor=N` needs no fixed name, port or actor id on the actor service
    assert "container_name" not in actor and "ports" not in actor
    assert "NASA_ACTOR_ID" not in actor.get("environment", {})
    for name, svc in services.items():
        assert svc["image"] == "nasa-td3"
        if name != "router":
            assert svc["environment"]["NASA_ZENOH_CONNECT"] == "tcp/router:7447"
            assert "router" in svc["depends_on"]
    assert (REPO / services["router"]["build"]["dockerfile"]).exists()
    # every service of a run gets the same config flags
    configs = [_config_flags(s["command"]) for n, s in services.items() if n != "router"]
    assert all(c == configs[0] for c in configs)
    assert "--algo" in configs[0] and "--task" in configs[0]


def _config_flags(command: list[str]) -> dict[str, str]:
    pairs = dict(zip(command[3::2], command[4::2], strict=False))
    return {k: v for k, v in pairs.items() if k in ("--task", "--algo", "--preset", "--steps")}


def test_every_command_is_a_module_with_working_help():
    services = load_compose()["services"]
    procs = {}
    for name, svc in services.items():
        cmd = svc["command"]
        assert cmd[:2] == ["python", "-m"] and cmd[2] == f"services.{name}"
        assert (REPO / "services" / name / "__main__.py").exists()
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", cmd[2], "--preset", "cpu-small", "--help"], cwd=REPO,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=120)
        assert proc.returncode == 0, f"{name}: {out}"
        for flag in (a for a in services[name]["command"][3:] if a.startswith("--")):
            assert re.search(rf"{re.escape(flag)}\b", out), f"{name} --help does not list {flag}"
