"""deploy/k8s/: the manifests are valid against the Kubernetes schemas (kubernetes-validate), and
the three ways to run the system -- `nasa up`, compose and Kubernetes -- start the same roles with
the same commands and config flags, so none of them can drift from the others."""

from __future__ import annotations

import re
from pathlib import Path

import kubernetes_validate
import pytest
from deploy_files import (
    CONFIG_FLAGS,
    K8S,
    REPO,
    ROLES,
    cpu_cores,
    flag_values,
    k8s_config_map,
    k8s_containers,
    load_compose,
    load_env,
    load_k8s,
)

from nasa.up import layout_of, parse_up, service_argv
from services.learner.learner import LearnerArgs
from shared.run_config import differing_fields
from shared.service import parse_with_preset

KUBERNETES_VERSION = "1.37.0"
# What each topology sets on its own, by design: nasa up numbers its actors (replicas draw an id),
# points --data at its run folder and computes the learner's threads from the host's cores.
OWN_FLAGS = {"actor": {"--actor-id"}}


def test_every_manifest_is_valid_against_the_schemas():
    docs = load_k8s()
    assert {d["kind"] for d in docs} >= {"ConfigMap", "Deployment", "StatefulSet", "Service"}
    for doc in docs:
        kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)


def test_the_validator_rejects_a_broken_manifest():
    (actor,) = [d for d in load_k8s() if d["metadata"]["name"] == "actor"]
    actor["spec"]["template"]["spec"]["containers"][0]["comand"] = ["python"]
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(actor, KUBERNETES_VERSION, strict=True)


def test_manifests_have_the_topology():
    docs = load_k8s()
    kinds = {d["metadata"]["name"]: d["kind"] for d in docs if d["kind"] != "Service"}
    assert kinds == {"nasa-td3-config": "ConfigMap", "router": "Deployment", "replay": "StatefulSet",
                     "learner": "StatefulSet", "evaluator": "Deployment", "actor": "Deployment"}
    services = {d["metadata"]["name"]: d for d in docs if d["kind"] == "Service"}
    assert [p["port"] for p in services["router"]["spec"]["ports"]] == [7447]
    assert [p["port"] for p in services["learner-status"]["spec"]["ports"]] == [8000]
    by_name = {d["metadata"]["name"]: d for d in docs}
    for name in ("replay", "learner"):  # a volume of its own, mounted where --data points
        (claim,) = by_name[name]["spec"]["volumeClaimTemplates"]
        mount = by_name[name]["spec"]["template"]["spec"]["containers"][0]["volumeMounts"][0]
        assert mount == {"name": claim["metadata"]["name"], "mountPath": "/data"}
    evaluator = by_name["evaluator"]["spec"]["template"]["spec"]  # its pictures: a scratch volume
    assert evaluator["containers"][0]["volumeMounts"][0] == {"name": "media", "mountPath": "/data"}
    assert {"name": "media", "emptyDir": {}} in evaluator["volumes"]
    # one evaluator per run: a rolling update would start the new one beside the old
    assert by_name["evaluator"]["spec"]["strategy"] == {"type": "Recreate"}
    assert by_name["actor"]["spec"]["replicas"] == int(load_env()["ACTORS"])
    # the GPU request is there for whoever turns it on
    assert "nvidia.com/gpu: 1" in (K8S / "learner.yaml").read_text()
    for doc in docs:
        if doc["kind"] in ("Deployment", "StatefulSet"):
            assert doc["spec"]["template"]["spec"]["securityContext"]["runAsNonRoot"] is True


def _up_argv(env: dict[str, str]) -> tuple[dict[str, list[str]], object]:
    """nasa up's service commands and the run config it resolves, for the .env's settings."""
    cmd, _ = parse_up(["--task", env["TASK"], "--algo", env["ALGO"], "--seed", env["SEED"],
                       "--steps", env["STEPS"], "--device", env["DEVICE"], "--preset", env["PRESET"]])
    roles: dict[str, list[str]] = {}
    for name, argv in service_argv(cmd, Path("/data"), layout_of(cmd, gpu=False)).items():
        roles.setdefault(name.split("-")[0], argv)  # actor-0, actor-1, ...: one is enough
    return roles, cmd.config


def test_nasa_up_compose_and_kubernetes_run_the_same_commands():
    env = load_env()
    up, up_config = _up_argv(env)
    compose = {n: s["command"] for n, s in load_compose()["services"].items() if n in ROLES}
    k8s = {n: c["command"] + c["args"] for n, c in k8s_containers(load_k8s()).items()}
    # nasa up runs the router inside its own process; the other roles are the same modules
    assert set(compose) == set(k8s) == set(ROLES) == {*up, "router"}
    assert compose["router"] == k8s["router"]
    for role in up:
        assert compose[role][:3] == k8s[role][:3] == ["python", "-m", f"services.{role}"]
        theirs, kube = flag_values(compose[role][3:]), flag_values(k8s[role][3:])
        assert set(theirs) == set(kube), role
        for flag in (*CONFIG_FLAGS, "--data", "--device", "--port"):
            assert theirs.get(flag) == kube.get(flag), (role, flag)
    # nasa up hands its services a config file; compose and k8s pass flags that resolve to the same config
    args, _ = parse_with_preset(LearnerArgs, compose["learner"][3:], "learner")
    assert differing_fields(args.config, up_config) == []


def test_kubernetes_and_compose_share_image_settings_and_checks():
    env = load_env()
    docs = load_k8s()
    values = k8s_config_map(docs)
    for key, value in values.items():
        assert value == env[key], key
    compose = load_compose()["services"]
    for role, container in k8s_containers(docs).items():
        assert container["image"] == compose[role]["image"] == env["IMAGE"]
        probes = [container.get(p) for p in ("readinessProbe", "livenessProbe")]
        execs = [p["exec"]["command"] for p in probes if p and "exec" in p]
        assert execs or role == "learner", f"{role}: no probe runs compose's check"
        for command in execs:  # the same per-role check compose runs
            assert command == compose[role]["healthcheck"]["test"][1:]
        if role == "learner":
            assert all(p["httpGet"]["path"] == "/healthz" for p in probes)


def test_every_pod_can_log_in_from_the_auth_secret():
    """Logins stay off by default, as in compose; a Secret turns them on for every pod at once,
    mounted where compose mounts its auth folder, readable by the image's user only."""
    docs = load_k8s()
    assert k8s_config_map(docs)["NASA_ZENOH_AUTH"] == load_env()["NASA_ZENOH_AUTH"] == ""
    compose_mount = load_compose()["services"]["actor"]["volumes"]
    assert any(str(v).endswith(":/run/nasa-auth:ro") for v in compose_mount)
    workloads = [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]
    assert len(workloads) == 5
    for doc in workloads:
        pod = doc["spec"]["template"]["spec"]
        (volume,) = [v for v in pod["volumes"] if v["name"] == "auth"]
        secret = {k: v for k, v in volume["secret"].items() if k != "items"}
        assert secret == {"secretName": "nasa-td3-auth", "optional": True, "defaultMode": 0o440}
        assert pod["securityContext"]["fsGroup"] == pod["securityContext"]["runAsGroup"] == 1000
        (container,) = pod["containers"]
        assert {"name": "auth", "mountPath": "/run/nasa-auth", "readOnly": True} in container["volumeMounts"]
        # the router reads NASA_ZENOH_AUTH too, as every client does
        assert container["envFrom"] == [{"configMapRef": {"name": "nasa-td3-config"}}]
    (learner,) = [d for d in workloads if d["metadata"]["name"] == "learner"]
    env = {e["name"]: e for e in learner["spec"]["template"]["spec"]["containers"][0]["env"]}
    assert env["NASA_API_TOKEN"]["valueFrom"]["secretKeyRef"] == {
        "name": "nasa-td3-auth", "key": "api-token", "optional": True}


AUTH_MOUNT = "/run/nasa-auth"


def _secret_keys_of_the_docs() -> list[Path]:
    """The files `kubectl create secret generic nasa-td3-auth` gets in docs/deployment.md, braces
    expanded as bash does; each is a key under its own name."""
    text = (REPO / "docs" / "deployment.md").read_text()
    command = text[text.index("kubectl create secret generic nasa-td3-auth"):]
    command = command[: command.index("\n# then")]
    files = []
    for arg in re.findall(r"--from-file=(\S+)", command):
        if match := re.fullmatch(r"(.*)\{(.*)\}", arg):
            files += [match.group(1) + name for name in match.group(2).split(",")]
        else:
            files.append(arg)
    return [Path(f) for f in files]


def _mounted(folder: Path, made: Path, pod: dict) -> Path:
    """The auth folder a pod sees: its volume's items of the Secret whose files are in `made`."""
    (volume,) = [v for v in pod["volumes"] if v["name"] == "auth"]
    for item in volume["secret"]["items"]:
        assert "/" not in item["key"]  # a Secret's keys cannot hold one
        target = folder / item["path"]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes((made / item["key"]).read_bytes())
    return folder


def test_each_pod_logs_in_and_loads_its_certificates_from_the_secret_as_the_docs_make_it(tmp_path):
    """The Secret's keys are file names; each pod's items put them where the services read them
    (users.txt, the router's acl.json, tls/ca.pem and the role's own tls/<role>.pem and .key)."""
    import zenoh

    from shared import zenoh_auth, zenoh_tls

    auth = tmp_path / "auth"  # `nasa auth init` and `nasa auth tls --host router`, as the docs say
    zenoh_auth.init(auth, "default")
    zenoh_tls.init(auth, ["router"])
    files = _secret_keys_of_the_docs()
    secret = tmp_path / "secret"  # kubectl's --from-file: the key is the file's name
    secret.mkdir()
    for file in files:
        assert file.parts[0] == "deploy" and file.parts[1] == "auth", file
        (secret / file.name).write_bytes((auth / Path(*file.parts[2:])).read_bytes())
    assert zenoh_tls.TLS_DIR + "/ca.key" not in {"/".join(f.parts[2:]) for f in files}
    for container in k8s_containers(load_k8s()).values():  # where NASA_ZENOH_AUTH is to point
        assert {"name": "auth", "mountPath": AUTH_MOUNT, "readOnly": True} in container["volumeMounts"]
    docs = (REPO / "docs" / "deployment.md").read_text()
    assert f"NASA_ZENOH_AUTH: {AUTH_MOUNT} in deploy/k8s/config.yaml" in docs
    for doc in load_k8s():
        if doc["kind"] not in ("Deployment", "StatefulSet"):
            continue
        role, pod = doc["metadata"]["name"], doc["spec"]["template"]["spec"]
        folder = _mounted(tmp_path / "pods" / role, secret, pod)
        config = zenoh.Config()
        if role == "router":
            zenoh_auth.apply_router(config, folder)
            zenoh_tls.apply_router(config, folder)
        else:
            zenoh_auth.apply_client(config, folder, role)
            zenoh_tls.apply_client(config, folder, role)
        other = "actor" if role != "actor" else "learner"
        assert not (folder / zenoh_tls.TLS_DIR / f"{other}.key").exists()  # its own key only


def test_without_certificates_in_the_secret_each_pod_still_logs_in(tmp_path):
    """The Secret made without `nasa auth tls`: the items it lacks are left out (optional)."""
    import zenoh

    from shared import zenoh_auth

    zenoh_auth.init(tmp_path / "auth", "default")
    for doc in load_k8s():
        if doc["kind"] not in ("Deployment", "StatefulSet"):
            continue
        (volume,) = [v for v in doc["spec"]["template"]["spec"]["volumes"] if v["name"] == "auth"]
        assert volume["secret"]["optional"] is True
        folder = tmp_path / "pods" / doc["metadata"]["name"]
        folder.mkdir(parents=True)
        for item in volume["secret"]["items"]:
            if (tmp_path / "auth" / item["key"]).exists():
                (folder / item["path"]).write_bytes((tmp_path / "auth" / item["key"]).read_bytes())
        if doc["metadata"]["name"] == "router":
            zenoh_auth.apply_router(zenoh.Config(), folder)
        else:
            zenoh_auth.apply_client(zenoh.Config(), folder, doc["metadata"]["name"])


def test_every_container_has_requests_and_limits_and_the_learner_the_cores():
    containers = k8s_containers(load_k8s())
    for role, container in containers.items():
        resources = container["resources"]
        assert {"cpu", "memory"} <= set(resources["requests"]), role
        assert "memory" in resources["limits"], role
    for role in ("actor", "evaluator"):  # one core each
        assert cpu_cores(containers[role]["resources"]["limits"]["cpu"]) == 1
    learner = containers["learner"]
    cores = cpu_cores(learner["resources"]["limits"]["cpu"])
    assert cpu_cores(learner["resources"]["requests"]["cpu"]) == cores
    others = [c["resources"]["requests"]["cpu"] for r, c in containers.items() if r != "learner"]
    assert all(cores > cpu_cores(cpu) for cpu in others)
    # its torch threads are its cores, not the node's
    assert flag_values(learner["args"])["--threads"] == str(int(cores))
    (cpus,) = [e for e in learner["env"] if e["name"] == "LEARNER_CPUS"]
    assert cpus["valueFrom"]["resourceFieldRef"]["resource"] == "limits.cpu"
