"""Zenoh logins and access control on a real router on loopback, and the learner API's bearer token."""

from __future__ import annotations

import json
import os
import queue
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from fastapi.testclient import TestClient
from system_harness import REPO

from nasa.up import free_port
from services.learner.status_api import api_token, is_loopback, make_app
from shared import wire, zenoh_auth
from shared.service import EXIT_LOGIN_REFUSED
from shared.zenoh_session import open_client, open_router, token_up

RUN = "authrun"


@pytest.fixture
def auth_dir(tmp_path: Path) -> Path:
    return zenoh_auth.init(tmp_path / "auth", RUN)


@pytest.fixture
def router(auth_dir: Path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_router(endpoint, auth=auth_dir):
        yield endpoint


def login(endpoint: str, auth_dir: Path, role: str) -> zenoh.Session:
    return open_client(endpoint, timeout_s=10.0, role=role, auth=auth_dir)


def test_every_key_has_a_route() -> None:
    """A key added to Keys or BridgeKeys without a route would be denied to everyone under auth."""
    k, b = wire.Keys(wire.ANY, wildcard=True), wire.BridgeKeys(wire.ANY, wildcard=True)
    routed = {r.key for r in wire.routes()}
    plain = {v for name, v in vars(k).items() if name not in ("prefix", "run_id") and not v.endswith("*")}
    plain |= {k.insert(wire.ANY), k.ack(wire.ANY), k.actor_status(wire.ANY)}
    plain |= {v for name, v in vars(b).items() if name != "prefix"}
    assert plain - routed == set()
    for role in ("actor", "replay", "learner", "evaluator"):
        assert k.alive(role, "**") in routed
    assert {role for r in wire.routes() for role in (*r.senders, *r.receivers)} <= set(wire.ROLES)
    with pytest.raises(ValueError):
        wire.Keys(wire.ANY)  # a service's run id is never a wildcard


@pytest.mark.system  # a `nasa` subprocess
def test_init_writes_private_credentials_and_refuses_to_overwrite(tmp_path: Path) -> None:
    folder = tmp_path / "auth"
    out = subprocess.run([sys.executable, "-m", "nasa.cli", "auth", "init", str(folder), "--run-id", RUN],
                         cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    users = folder / zenoh_auth.USERS_FILE
    assert stat.S_IMODE(users.stat().st_mode) == 0o600
    creds = zenoh_auth.credentials(folder)
    assert set(creds) == set(zenoh_auth.AUTH_ROLES) and len(set(creds.values())) == len(creds)
    rules = json.loads((folder / zenoh_auth.ACL_FILE).read_text())
    assert rules["default_permission"] == "deny"
    keys = {key for rule in rules["rules"] for key in rule["key_exprs"]}
    assert all(key.startswith((f"nasa/{RUN}/", "nasa/bridge/")) or key == "nasa/**" for key in keys)
    again = subprocess.run([sys.executable, "-m", "nasa.cli", "auth", "init", str(folder)],
                           cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 2 and "--force" in again.stderr
    assert zenoh_auth.credentials(folder) == creds
    zenoh_auth.init(folder, RUN, force=True)
    assert zenoh_auth.credentials(folder)["actor"] != creds["actor"]


@pytest.mark.system  # `nasa` subprocesses
def test_an_acl_from_an_older_wiring_is_remade_with_acl_only_keeping_the_passwords(tmp_path: Path) -> None:
    def nasa(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "nasa.cli", *argv], cwd=REPO, capture_output=True,
                              text=True)

    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    creds = zenoh_auth.credentials(folder)
    (folder / zenoh_auth.ACL_FILE).write_text("{}")  # as a version with other keys made it
    with pytest.raises(zenoh_auth.AuthError, match="--acl-only") as refused:
        zenoh_auth.check_acl(folder, RUN)
    argv = str(refused.value).split("`")[1].split()  # the command the refusal names, as a user runs it
    assert argv[:3] == ["nasa", "auth", "init"]
    out = nasa(*argv[1:])
    assert out.returncode == 0, out.stderr
    zenoh_auth.check_acl(folder, RUN)
    assert zenoh_auth.credentials(folder) == creds
    both = nasa("auth", "init", str(folder), "--acl-only", "--force")
    assert both.returncode == 2 and "one of the two" in both.stderr
    assert zenoh_auth.credentials(folder) == creds
    none = nasa("auth", "init", str(tmp_path / "new"), "--acl-only")
    assert none.returncode == 2 and "no " in none.stderr and not (tmp_path / "new").exists()


def test_router_refuses_a_wrong_or_missing_password(router: str, auth_dir: Path, tmp_path: Path) -> None:
    forged = tmp_path / "forged"
    forged.mkdir()
    (forged / zenoh_auth.USERS_FILE).write_text("actor:not-the-password\n")
    # A refused login says so, rather than "is it up?" (still a ZError: a supervisor retries).
    with pytest.raises(zenoh.ZError, match="is up but refused 'actor'"):
        open_client(router, timeout_s=1.0, role="actor", auth=forged)
    with pytest.raises(zenoh.ZError, match="is up but refused a session without a login"):
        open_client(router, timeout_s=1.0)  # no credentials at all
    with pytest.raises(zenoh.ZError, match="is it up"):
        open_client(f"tcp/127.0.0.1:{free_port()}", timeout_s=0.5, role="actor", auth=forged)
    with pytest.raises(zenoh_auth.AuthError):
        open_client(router, timeout_s=1.0, auth=auth_dir)  # a folder but no role
    with login(router, auth_dir, "actor") as session:
        assert session.info.zid() is not None


@pytest.mark.timeout(180)
@pytest.mark.parametrize(("argv", "prog", "role"), [
    (["services.actor", "--actor-id", "0"], "python -m services.actor", "actor"),
    (["services.robot_bridge", "--bridge-id", "b0"], "robot_bridge", "bridge"),  # a main of its own
])
def test_a_service_whose_login_is_refused_exits_with_its_own_code(
    router: str, tmp_path: Path, argv: list[str], prog: str, role: str
) -> None:
    # Not exit 1 (the router unreachable, worth retrying): `nasa up` does not restart it.
    other = zenoh_auth.init(tmp_path / "other", RUN)  # the same roles, other passwords
    env = {**os.environ, "NASA_ZENOH_CONNECT": router, "NASA_RUN_ID": RUN, "NASA_ZENOH_AUTH": str(other),
           "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    done = subprocess.run([sys.executable, "-m", *argv], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=150)
    assert done.returncode == EXIT_LOGIN_REFUSED == 3, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith(
        f"{prog}: error: the Zenoh router at {router} is up but refused '{role}''s login")


def into(q: queue.Queue):  # noqa: ANN201
    return lambda sample: q.put((str(sample.key_expr), sample.payload.to_bytes()))


def until(q: queue.Queue, last: tuple[str, bytes]) -> list[tuple[str, bytes]]:
    """What arrives up to and including `last`."""
    seen = []
    while not seen or seen[-1] != last:
        seen.append(q.get(timeout=20.0))
    return seen


def wait_routed(sender: zenoh.Session, key: str, q: queue.Queue) -> None:
    """Until the subscriptions have reached the router: a put from `sender` on `key` arrives."""
    while True:
        sender.put(key, b"probe")
        try:
            q.get(timeout=0.5)
            return
        except queue.Empty:
            continue


def test_a_role_puts_only_on_its_keys(router: str, auth_dir: Path) -> None:
    """An actor's forged stop, eval result and evaluation weights never arrive; its status does, and
    so do the learner's evaluation weights. Messages from one session go through the router in
    order, so once the actor's status has arrived, anything it sent before would have been passed
    on already."""
    k = wire.Keys(RUN)
    at_learner: queue.Queue[tuple[str, bytes]] = queue.Queue()
    at_evaluator: queue.Queue[tuple[str, bytes]] = queue.Queue()
    with (login(router, auth_dir, "actor") as actor, login(router, auth_dir, "learner") as learner,
          login(router, auth_dir, "evaluator") as evaluator):
        subs = [learner.declare_subscriber(key, into(at_learner))
                for key in (k.stop, k.eval_result, k.actor_status_all)]
        subs.append(evaluator.declare_subscriber(k.eval_weights, into(at_evaluator)))
        wait_routed(actor, k.actor_status(0), at_learner)
        actor.put(k.eval_weights, b"forged weights")
        actor.put(k.stop, b"forged stop")
        actor.put(k.eval_result, b"forged result")
        actor.put(k.actor_status(0), b"status")
        assert {key for key, _ in until(at_learner, (k.actor_status(0), b"status"))} == {k.actor_status(0)}
        # The forged weights went through the router before the status the learner has now.
        learner.put(k.eval_weights, b"real weights")
        assert until(at_evaluator, (k.eval_weights, b"real weights")) == [(k.eval_weights, b"real weights")]
        for sub in subs:
            sub.undeclare()


def test_only_the_learner_and_an_operator_stop_the_run(router: str, auth_dir: Path) -> None:
    k = wire.Keys(RUN)
    at_learner: queue.Queue[tuple[str, bytes]] = queue.Queue()
    with (login(router, auth_dir, "learner") as learner, login(router, auth_dir, "evaluator") as evaluator,
          login(router, auth_dir, "operator") as operator):
        subs = [learner.declare_subscriber(key, into(at_learner)) for key in (k.stop, k.eval_result)]
        wait_routed(evaluator, k.eval_result, at_learner)
        evaluator.put(k.stop, b"forged stop")
        evaluator.put(k.eval_result, b"result")
        assert {key for key, _ in until(at_learner, (k.eval_result, b"result"))} == {k.eval_result}
        operator.put(k.stop, b"operator's stop")
        assert until(at_learner, (k.stop, b"operator's stop")) == [(k.stop, b"operator's stop")]
        for sub in subs:
            sub.undeclare()


def test_only_the_bridge_confirms_an_estop_and_only_the_operator_hears_it(
        router: str, auth_dir: Path, monkeypatch) -> None:  # noqa: ANN001
    """Under the ACL a bridge's acknowledgement reaches the operator's `estop`; an actor can neither
    forge one for the operator nor hear the bridge's."""
    from services.robot_bridge import operate
    from services.robot_bridge.server import BridgeServer
    from shared.gripper.sim import ValveSim

    b = wire.BridgeKeys("g1")
    forged = wire.encode(wire.BridgeEStopAck("x", True, "estop", [], "forger"))
    at_operator: queue.Queue[tuple[str, bytes]] = queue.Queue()
    at_actor: queue.Queue[tuple[str, bytes]] = queue.Queue()
    monkeypatch.setenv("NASA_ZENOH_AUTH", str(auth_dir))
    sim = ValveSim("gripper-valve", seed=0, image_size=32, render_quality="fast")
    try:
        with (login(router, auth_dir, "bridge") as bridge, login(router, auth_dir, "actor") as actor,
              login(router, auth_dir, "actor") as listener, login(router, auth_dir, "operator") as operator):
            server = BridgeServer(bridge, "g1", sim, "gripper-valve", log=lambda _: None)
            with server.serve():
                ack, deadline = None, time.monotonic() + 30.0
                while ack is None:  # until the bridge's subscriber has reached the router
                    assert time.monotonic() < deadline, "no acknowledgement reached the operator"
                    ack = operate.send_estop("g1", True, "test", router, wait_s=1.0)
                assert (ack.engage, ack.state, ack.unreached) == (True, "estop", []) and server.estopped
                subs = [operator.declare_subscriber(b.estop_ack, into(at_operator)),
                        listener.declare_subscriber(b.estop_ack, into(at_actor))]
                wait_routed(bridge, b.estop_ack, at_operator)
                actor.put(b.estop_ack, forged)
                bridge.put(b.estop_ack, b"real")
                # The forged one went through the router before the bridge's, which is all that came.
                assert until(at_operator, (b.estop_ack, b"real")) == [(b.estop_ack, b"real")]
                assert at_actor.empty()
                for sub in subs:
                    sub.undeclare()
    finally:
        sim.close()


def test_an_evaluator_plays_on_a_bridge_of_its_own_under_the_acl(router: str, auth_dir: Path) -> None:
    """`nasa up --bridge stand-in` (logins on by default) starts a bridge for the evaluator: logged in
    as the evaluator, it sees the bridge's token and asks its spec, resets and steps."""
    from services.robot_bridge.client import BridgeEnv, BridgePresence
    from services.robot_bridge.server import BridgeServer
    from shared.gripper.sim import ValveSim

    sim = ValveSim("gripper-valve", seed=0, image_size=32, render_quality="fast")
    try:
        with (login(router, auth_dir, "bridge") as bridge, login(router, auth_dir, "evaluator") as evaluator,
              BridgeServer(bridge, "g1", sim, "gripper-valve", log=lambda _: None).serve(),
              BridgePresence(evaluator, "g1") as presence):
            deadline = time.monotonic() + 10.0
            while not presence.present:
                assert time.monotonic() < deadline, "the evaluator never saw its bridge's token"
                time.sleep(0.05)
            env = BridgeEnv(evaluator, "g1", timeout_s=10.0)
            frame, *_ = env.reset()
            frame, reward, _, _ = env.step(np.zeros(env.action_dim, np.float32))
            assert frame.shape == (3, 32, 32) and -1.0 <= reward <= 0.0
    finally:
        sim.close()


def test_an_actor_cannot_sample_the_replay(router: str, auth_dir: Path) -> None:
    k = wire.Keys(RUN)

    def answer(query: zenoh.Query) -> None:
        query.reply(k.sample, b"batch")

    with (login(router, auth_dir, "replay") as replay, login(router, auth_dir, "learner") as learner,
          login(router, auth_dir, "actor") as actor):
        queryable = replay.declare_queryable(k.sample, answer)
        replies: list = []
        while not replies:  # the queryable is known to the router once the learner gets an answer
            replies = [r.ok.payload.to_bytes() for r in learner.get(k.sample, timeout=2.0) if r.ok]
        assert replies == [b"batch"]
        assert [r for r in actor.get(k.sample, timeout=2.0) if r.ok] == []
        queryable.undeclare()


def test_liveliness_tokens_follow_the_routes(router: str, auth_dir: Path) -> None:
    """The replay's token is seen by actors and by the replay's own healthcheck, not by the evaluator;
    an actor cannot pose as the replay by declaring its token."""
    k = wire.Keys(RUN)

    def seen(session: zenoh.Session) -> bool:
        return token_up(session, k.alive("replay", 0))

    with (login(router, auth_dir, "replay") as replay, login(router, auth_dir, "actor") as actor,
          login(router, auth_dir, "evaluator") as evaluator, login(router, auth_dir, "learner") as learner):
        forged = actor.liveliness().declare_token(k.alive("replay", 0))
        own = actor.liveliness().declare_token(k.alive("actor", 0, 1))
        # The actor's own token reached the router after the forged one, on the same link.
        while not token_up(learner, k.alive_actors):
            pass
        assert not seen(replay)
        forged.undeclare()
        own.undeclare()
        token = replay.liveliness().declare_token(k.alive("replay", 0))
        while not seen(actor):
            pass
        with login(router, auth_dir, "replay") as healthcheck:
            assert seen(healthcheck)
        assert not seen(evaluator)
        token.undeclare()


def test_an_actor_sees_the_tokens_of_its_own_id(router: str, auth_dir: Path) -> None:
    """A second launch of an actor id is told apart by the first through the id's tokens."""
    k = wire.Keys(RUN)
    with login(router, auth_dir, "actor") as first, login(router, auth_dir, "actor") as again:
        token = again.liveliness().declare_token(k.alive("actor", 0, 2))
        deadline = time.monotonic() + 10.0
        same_id = k.alive("actor", 0) + "/*"
        while not token_up(first, same_id):
            assert time.monotonic() < deadline, "an actor never saw the token of its own id"
        token.undeclare()


@pytest.mark.parametrize("role", ["replay", "learner", "evaluator", "bridge"])
def test_a_service_sees_the_token_of_another_serving_its_role(router: str, auth_dir: Path, role: str) -> None:
    """A second replay, learner, evaluator or bridge (of one id) refuses to serve only if it can
    see the first one's token (shared.faults.claim_role)."""
    key = wire.BridgeKeys("g1").alive if role == "bridge" else wire.Keys(RUN).alive(role, 0)
    with login(router, auth_dir, role) as first, login(router, auth_dir, role) as again:
        token = first.liveliness().declare_token(key)
        deadline = time.monotonic() + 10.0
        while not token_up(again, key):
            assert time.monotonic() < deadline, f"a {role} never saw the token of another {role}"
        token.undeclare()


def test_the_learner_sees_the_evaluators_token_and_an_actor_does_not(router: str, auth_dir: Path) -> None:
    """At the end of a run the learner waits for the last evaluation while an evaluator is alive."""
    k = wire.Keys(RUN)

    def seen(session: zenoh.Session) -> bool:
        return token_up(session, k.alive_evaluators)

    with (login(router, auth_dir, "evaluator") as evaluator, login(router, auth_dir, "learner") as learner,
          login(router, auth_dir, "actor") as actor):
        token = evaluator.liveliness().declare_token(k.alive("evaluator", 0))
        deadline = time.monotonic() + 10.0
        while not seen(learner):
            assert time.monotonic() < deadline, "the learner never saw the evaluator's token"
        assert not seen(actor)
        token.undeclare()


@pytest.mark.system  # a service process
def test_a_router_without_its_acl_refuses_to_start(tmp_path: Path) -> None:
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    (folder / zenoh_auth.ACL_FILE).unlink()
    out = subprocess.run([sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{free_port()}",
                          "--auth", str(folder)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "acl.json" in out.stderr


def older_wiring_acl(folder: Path) -> None:
    """Write the ACL a version made before bridges answered e-stops (no `estop_ack` route)."""
    older = tuple(r for r in wire.routes(RUN) if not r.key.endswith("/estop_ack"))
    (folder / zenoh_auth.ACL_FILE).write_text(json.dumps(zenoh_auth.acl(older)))


def test_a_router_takes_the_acl_of_one_run_or_of_every_run_but_not_an_older_wiring(tmp_path: Path) -> None:
    """A router is not told its runs: an ACL made today for any one run, or for every run, is its own."""
    zenoh_auth.check_acl(zenoh_auth.init(tmp_path / "one", RUN))
    zenoh_auth.check_acl(zenoh_auth.init(tmp_path / "every", wire.ANY))
    folder = zenoh_auth.init(tmp_path / "older", RUN)
    older_wiring_acl(folder)
    with pytest.raises(zenoh_auth.AuthError, match=f"--run-id {RUN} --acl-only"):
        zenoh_auth.check_acl(folder)


def start_router(folder: Path, run_id: str | None) -> tuple[bool, list[str]]:
    """A router process on `folder` under NASA_RUN_ID `run_id` (None: unset): whether it came up
    (it is stopped then), and what it wrote until it did or exited."""
    env = {k: v for k, v in os.environ.items() if k != "NASA_RUN_ID"}
    if run_id is not None:
        env["NASA_RUN_ID"] = run_id
    cmd = [sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{free_port()}",
           "--auth", str(folder)]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        while line := proc.stderr.readline():  # type: ignore[union-attr]
            lines.append(line)
            if "listening on" in line:
                return True, lines
        assert proc.wait(timeout=60) == 2, lines
        return False, lines
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.mark.system  # router processes
def test_a_router_told_its_run_refuses_an_acl_made_for_another(tmp_path: Path) -> None:
    """Started on it, the router would deny every service of its run without a word."""
    other = zenoh_auth.init(tmp_path / "other", "another-run")
    listened, lines = start_router(other, RUN)
    assert not listened and lines == [
        f"router: error: {other / zenoh_auth.ACL_FILE} is made for run another-run, not {RUN}: `nasa auth "
        f"init {other} --run-id {RUN} --acl-only` makes it anew and keeps the passwords\n"]
    assert start_router(other, "another-run")[0]
    assert start_router(other, None)[0]  # not told its run: any one run's ACL is its own
    assert start_router(zenoh_auth.init(tmp_path / "every", wire.ANY), RUN)[0]


@pytest.mark.system  # router processes
def test_a_router_told_an_invalid_run_id_says_what_one_is_and_exits_before_it_listens(tmp_path: Path) -> None:
    """With its auth folder the refusal named `nasa auth init ... --run-id a/b`, which refuses that id."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    for auth in (["--auth", str(folder)], []):
        port = free_port()
        out = subprocess.run([sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{port}",
                              *auth], cwd=REPO, env={**os.environ, "NASA_RUN_ID": "a/b"}, capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 2 and out.stderr == (
            "router: error: NASA_RUN_ID: run id 'a/b' may hold only letters, digits, '_', '.', '-'\n")
    assert start_router(folder, RUN)[0]


@pytest.mark.system  # router processes
def test_a_router_refuses_an_acl_from_an_older_wiring_and_starts_once_it_is_remade(tmp_path: Path) -> None:
    """Zenoh would enforce it as it is, dropping the newer keys' messages (a bridge's answer to an
    e-stop) without a word: the router exits 2 naming the command that remakes it, passwords kept."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    creds = zenoh_auth.credentials(folder)
    older_wiring_acl(folder)
    cmd = [sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{free_port()}",
           "--auth", str(folder)]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=20)
    assert out.returncode == 2 and "older wiring" in out.stderr, out.stderr
    argv = out.stderr.split("`")[1].split()  # the command the refusal names, as a user runs it
    fixed = subprocess.run([sys.executable, "-m", "nasa.cli", *argv[1:]], cwd=REPO, capture_output=True,
                           text=True, timeout=60)
    assert argv[:3] == ["nasa", "auth", "init"] and fixed.returncode == 0, fixed.stderr
    assert zenoh_auth.credentials(folder) == creds
    proc = subprocess.Popen(cmd, cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        lines: list[str] = []
        while not lines or "listening on" not in lines[-1]:
            line = proc.stderr.readline()  # type: ignore[union-attr]
            assert line, "".join(lines)  # it ended without listening
            lines.append(line)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


# -- the learner's HTTP controls ---------------------------------------------------------------------


def control_app(token: str | None) -> tuple[TestClient, list[str]]:
    done: list[str] = []
    controls = {name: (lambda name=name: done.append(name) or "ok") for name in ("checkpoint", "stop")}
    app = make_app(lambda: {"updates": 1}, lambda: [], metrics=lambda: b"nasa_updates 1\n",
                   controls=controls, token=token)
    return TestClient(app), done


def test_controls_need_the_bearer_token() -> None:
    client, done = control_app("s3cret-token")
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "s3cret-token"},
                    {"Authorization": "Bearer s3cret-token-and-more"}):
        r = client.post("/control/checkpoint", headers=headers)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert done == []
    r = client.post("/control/stop", headers={"Authorization": "Bearer s3cret-token"})
    assert r.status_code == 202 and r.json()["control"] == "stop"
    assert done == ["stop"]
    for path in ("/status", "/healthz", "/metrics", "/"):
        assert client.get(path).status_code == 200, path
    assert client.get("/control/stop").status_code == 405  # a control is never a GET


def test_the_bearer_scheme_is_case_insensitive_as_in_http() -> None:
    client, done = control_app("s3cret-token")
    def post(header: str) -> int:
        return client.post("/control/checkpoint", headers={"Authorization": header}).status_code

    for header in ("bearer s3cret-token", "BEARER s3cret-token", "Bearer  s3cret-token"):
        assert post(header) == 202, header
    for header in ("Basic s3cret-token", "bearer", "bearer s3cret", "Bearers3cret-token"):
        assert post(header) == 401, header
    assert done == ["checkpoint"] * 3


def test_controls_are_open_without_a_token() -> None:
    client, done = control_app(None)
    assert client.post("/control/checkpoint").status_code == 202
    assert done == ["checkpoint"]


def test_the_token_comes_from_the_environment_or_a_file(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.delenv("NASA_API_TOKEN", raising=False)
    path = tmp_path / "token"
    path.write_text("from-file\n")
    assert api_token(None) is None
    assert api_token(path) == "from-file"
    monkeypatch.setenv("NASA_API_TOKEN", "from-env")
    assert api_token(path) == "from-env"
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("10.0.0.5")
    assert os.environ["NASA_API_TOKEN"] == "from-env"


# -- compose ----------------------------------------------------------------------------------------


def test_compose_passes_auth_to_every_service_and_keeps_it_off_by_default() -> None:
    from deploy_files import DEPLOY, load_compose, load_env

    env = load_env()
    assert env["NASA_ZENOH_AUTH"] == "" and env["NASA_API_TOKEN"] == ""  # off, as under `nasa up`
    assert (DEPLOY / env["ZENOH_AUTH_DIR"]).is_dir()  # a bind mount of a missing folder would make one
    off = load_compose()["services"]
    on = load_compose({"NASA_ZENOH_AUTH": "/run/nasa-auth", "NASA_API_TOKEN": "t0ken"})["services"]
    for name, svc in on.items():
        assert svc["environment"]["NASA_ZENOH_AUTH"] == "/run/nasa-auth", name
        assert off[name]["environment"]["NASA_ZENOH_AUTH"] == "", name
        assert f"{env['ZENOH_AUTH_DIR']}:/run/nasa-auth:ro" in svc["volumes"], name
    for name in ("learner", "learner-gpu"):
        assert on[name]["environment"]["NASA_API_TOKEN"] == "t0ken"
        assert on[name]["environment"]["NASA_STATUS_HOST"] == "0.0.0.0"
    assert "NASA_API_TOKEN" not in on["actor"]["environment"]
    # TLS links: the router listens and every client connects where deploy/.env says
    tls = load_compose({"NASA_ZENOH_LISTEN": "tls/0.0.0.0:7447", "NASA_ZENOH_CONNECT": "tls/router:7447"})
    assert tls["services"]["router"]["environment"]["NASA_ZENOH_LISTEN"] == "tls/0.0.0.0:7447"
    assert off["router"]["environment"]["NASA_ZENOH_LISTEN"] == "tcp/0.0.0.0:7447"
    for name, svc in tls["services"].items():
        if name != "router":
            assert svc["environment"]["NASA_ZENOH_CONNECT"] == "tls/router:7447", name


def test_an_acl_for_another_run_or_an_older_wiring_is_refused(tmp_path: Path) -> None:
    zenoh_auth.check_acl(zenoh_auth.init(tmp_path / "mine", RUN), RUN)
    zenoh_auth.check_acl(zenoh_auth.init(tmp_path / "every", wire.ANY), RUN)
    other = zenoh_auth.init(tmp_path / "other", "another-run")
    with pytest.raises(zenoh_auth.AuthError, match=f"made for run another-run, not {RUN}: "):
        zenoh_auth.check_acl(other, RUN)
    stale = json.loads((other / zenoh_auth.ACL_FILE).read_text())
    stale["rules"] = stale["rules"][1:]
    (other / zenoh_auth.ACL_FILE).write_text(json.dumps(stale))
    with pytest.raises(zenoh_auth.AuthError):
        zenoh_auth.check_acl(other, "another-run")


def test_nasa_up_turns_logins_on_by_default_with_the_run_folders_own(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    from nasa.up import parse_up, up_auth
    from shared.config import ConfigError

    monkeypatch.delenv("NASA_ZENOH_AUTH", raising=False)
    data = tmp_path / "run"
    default, _ = parse_up([])
    assert default.zenoh_auth == "run"
    env: dict[str, str] = {}
    folder = up_auth(default, data, RUN, env)
    assert folder == data / "auth" and env["NASA_ZENOH_AUTH"] == str(folder.resolve())
    assert stat.S_IMODE((folder / zenoh_auth.USERS_FILE).stat().st_mode) == 0o600
    creds = zenoh_auth.credentials(folder)
    (folder / zenoh_auth.ACL_FILE).write_text("{}")  # made by an older version of the wiring
    up_auth(default, data, RUN, {})  # a resumed run keeps its credentials, and gets today's ACL
    assert zenoh_auth.credentials(folder) == creds
    zenoh_auth.check_acl(folder, RUN)
    off, _ = parse_up(["--zenoh-auth", "off"])
    env = {"NASA_ZENOH_AUTH": "/elsewhere"}
    assert up_auth(off, tmp_path / "other", RUN, env) is None and "NASA_ZENOH_AUTH" not in env
    assert not (tmp_path / "other").exists()
    (tmp_path / "a-file").write_text("")
    bad, _ = parse_up(["--zenoh-auth", str(tmp_path / "a-file")])
    with pytest.raises(ConfigError, match="cannot write the run's credentials"):
        up_auth(bad, data, RUN, {})
    monkeypatch.setenv("NASA_ZENOH_AUTH", str(tmp_path / "shared"))
    mine, _ = parse_up([])
    assert up_auth(mine, data, RUN, {}) == tmp_path / "shared"


@pytest.mark.parametrize("command", [["init"], ["tls", "--host", "example.org"]])
def test_nasa_auth_names_a_folder_it_cannot_write_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]) -> None:
    from nasa import cli

    afile = tmp_path / "afile"
    afile.write_text("")
    for folder, said in ((afile, f"{afile} is a file, not a folder"),
                         (afile / "auth", f"cannot write {afile / 'auth'}: "),
                         (Path("/proc/nasa-auth"), "cannot write /proc/nasa-auth: ")):
        with pytest.raises(SystemExit) as done:
            cli.main(["auth", command[0], str(folder), *command[1:]])
        err = capsys.readouterr().err
        assert done.value.code == 2 and err.startswith(f"nasa auth: error: {said}"), err
        assert len(err.strip().splitlines()) == 1


def test_nasa_auth_tls_takes_every_host_of_a_repeated_flag(tmp_path: Path) -> None:
    """`--host router --host lab-a` (as docs/deployment.md writes it): the router's certificate names
    both, not only the last one given."""
    from cryptography import x509

    from nasa import cli

    folder = tmp_path / "auth"
    cli.main(["auth", "tls", str(folder), "--host", "router", "--host", "lab-a.example.org"])
    cert = x509.load_pem_x509_certificate((folder / "tls" / "router.pem").read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {"router", "lab-a.example.org"} <= set(names.get_values_for_type(x509.DNSName))


@pytest.mark.system  # router processes
@pytest.mark.parametrize("damage", ["users-binary", "users-folder", "users-empty", "users-no-replay",
                                    "acl-folder", "acl-not-json", "acl-odd-json"])
def test_a_router_with_a_damaged_auth_folder_says_which_file_in_one_line(tmp_path: Path, damage: str) -> None:
    """Not a traceback, not Zenoh's parse error blamed on the port, and never a router that lets
    every client in unnamed (Zenoh's reading of an empty dictionary)."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    users, rules = folder / zenoh_auth.USERS_FILE, folder / zenoh_auth.ACL_FILE
    if damage == "users-binary":
        users.write_bytes(b"\xff\xfe\x00garbage")
    elif damage == "users-folder":
        users.unlink()
        users.mkdir()
    elif damage == "users-empty":
        users.write_text("")
    elif damage == "users-no-replay":
        users.write_text("".join(line + "\n" for line in users.read_text().splitlines()
                                 if not line.startswith("replay:")))
    elif damage == "acl-folder":
        rules.unlink()
        rules.mkdir()
    elif damage == "acl-odd-json":
        rules.write_text('{"rules": [{"key_exprs": 5}]}')
    else:
        rules.write_text("{not json")
    out = subprocess.run([sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{free_port()}",
                          "--auth", str(folder)], cwd=REPO, capture_output=True, text=True, timeout=20)
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert ("users.txt" if damage.startswith("users") else "acl.json") in out.stderr
    assert "cannot listen" not in out.stderr


def test_a_client_with_an_unreadable_users_file_gets_an_auth_error(tmp_path: Path) -> None:
    """A service names the file (exit 2) rather than dying on a UnicodeDecodeError or IsADirectoryError."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    (folder / zenoh_auth.USERS_FILE).write_bytes(b"actor:\xff\xfe\n")
    with pytest.raises(zenoh_auth.AuthError, match="users.txt"):
        open_client("tcp/127.0.0.1:1", timeout_s=0.1, role="actor", auth=folder)


@pytest.mark.parametrize("text", ['{"enabled": tr', '{"rules": [{"key_exprs": 5}]}',
                                  '{"rules": [7, {"key_exprs": true}, {"key_exprs": null}]}', '[1]'])
def test_a_damaged_acl_is_refused_like_a_missing_one(tmp_path: Path, text: str) -> None:
    """Not JSON, or JSON of another shape (a hand edit): refused with the command that remakes it,
    by `nasa up` (its run id) and by a router (none), not a traceback."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    (folder / zenoh_auth.ACL_FILE).write_text(text)
    for run_id in (RUN, None):
        with pytest.raises(zenoh_auth.AuthError, match="--acl-only"):
            zenoh_auth.check_acl(folder, run_id)


def test_a_missing_or_damaged_acl_is_refused_whatever_run_is_named(tmp_path: Path) -> None:
    """No run id makes a missing or unreadable ACL pass, not even one no run can have (for which
    there is no ACL to compare it with)."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    rules = folder / zenoh_auth.ACL_FILE
    for damage in ("missing", "not json"):
        rules.unlink(missing_ok=True)
        if damage == "not json":
            rules.write_text('{"enabled": tr')
        for run_id in (RUN, None, "not/a run"):
            with pytest.raises(zenoh_auth.AuthError, match="--acl-only"):
                zenoh_auth.check_acl(folder, run_id)


def test_rotation_over_a_stale_temporary_file_keeps_the_credentials_private(tmp_path: Path) -> None:
    """A users.tmp left world-readable by an interrupted init must not hand its mode to users.txt."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    stale = (folder / zenoh_auth.USERS_FILE).with_suffix(".tmp")
    stale.write_text("")
    stale.chmod(0o644)
    zenoh_auth.init(folder, RUN, force=True)
    assert stat.S_IMODE((folder / zenoh_auth.USERS_FILE).stat().st_mode) == 0o600


@pytest.mark.system  # a router process
def test_a_router_warns_of_credentials_every_user_can_read(tmp_path: Path) -> None:
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    (folder / zenoh_auth.USERS_FILE).chmod(0o644)
    # Told the folder's run: a NASA_RUN_ID left in the caller's environment would have it refused.
    listened, lines = start_router(folder, RUN)
    assert listened and any("readable by every user" in line for line in lines), "".join(lines)


def test_nasa_up_names_a_run_folder_whose_access_rules_it_cannot_write(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from nasa.up import up_auth
    from shared.config import ConfigError

    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    (folder / zenoh_auth.ACL_FILE).unlink()
    (folder / zenoh_auth.ACL_FILE).mkdir()  # cannot be replaced by a file
    with pytest.raises(ConfigError, match="cannot write the run's access rules"):
        up_auth(SimpleNamespace(zenoh_auth="run"), tmp_path, RUN, {})


def test_checkpoint_requests_join_the_pending_one_and_are_refused_right_after(monkeypatch) -> None:  # noqa: ANN001
    """A client posting in a loop must not have the learner write checkpoints back to back."""
    from services.learner import status_api

    requests = status_api.CheckpointRequests()
    app = make_app(lambda: {"updates": 1}, lambda: [], controls={"checkpoint": requests.ask}, token="t")
    client = TestClient(app)
    auth = {"Authorization": "Bearer t"}
    first = client.post("/control/checkpoint", headers=auth)
    assert first.status_code == 202 and "next update" in first.json()["done"] and requests.pending()
    joined = client.post("/control/checkpoint", headers=auth)
    assert joined.status_code == 202 and "already pending" in joined.json()["done"]
    assert client.post("/control/checkpoint").status_code == 401  # the token still comes first
    requests.written()  # the loop wrote it: one checkpoint for the three requests
    assert not requests.pending()
    soon = client.post("/control/checkpoint", headers=auth)
    assert soon.status_code == 429 and "ask again in" in soon.json()["detail"]
    assert int(soon.headers["retry-after"]) >= 1 and not requests.pending()
    monkeypatch.setattr(status_api, "CHECKPOINT_EVERY_S", 0.0)
    again = client.post("/control/checkpoint", headers=auth)
    assert again.status_code == 202 and requests.pending()
