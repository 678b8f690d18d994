"""Zenoh authentication and access control: one credential per role, one access-control list.

An auth folder (`nasa auth init DIR`) holds:

- `users.txt`: one `role:password` line per role (mode 0600). The router reads it whole as its
  Zenoh user/password dictionary; a client reads its own role's line from it. A host that runs
  one role only needs a users.txt holding that role's line.
- `acl.json`: the router's `access_control` section, made from `shared.wire.routes()`: each role
  may put, subscribe, query, answer and declare liveliness tokens on its own keys only; anything
  else is denied at the router (the message never reaches a subscriber).

With NASA_ZENOH_AUTH=DIR (or the router's --auth DIR) sessions authenticate; without it they
connect with no credentials, as before. A client refused by the router (wrong or no password)
fails to open with SessionRefused (shared/zenoh_session.py): the router's port is open, the login not.
"""

from __future__ import annotations

import json
import os
import secrets
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

from shared.files import replace_text
from shared.wire import ANY, PREFIX, PUT, QUERY, ROLES, TOKEN, Route, routes

if TYPE_CHECKING:
    import zenoh

USERS_FILE = "users.txt"
ACL_FILE = "acl.json"
ROUTER = "router"
AUTH_ROLES = (*ROLES, ROUTER)
"""Every role with a credential; `router` is the one routers of several sites use between them."""

# What a role's side of a route may send to the router (ingress) and receive from it (egress).
_INGRESS = {
    (PUT, "send"): ("put",), (PUT, "receive"): ("declare_subscriber",),
    (QUERY, "send"): ("declare_queryable", "reply"), (QUERY, "receive"): ("query",),
    (TOKEN, "send"): ("liveliness_token",),
    (TOKEN, "receive"): ("declare_liveliness_subscriber", "liveliness_query"),
}
_EGRESS = {
    (PUT, "send"): ("declare_subscriber",), (PUT, "receive"): ("put",),
    (QUERY, "send"): ("query",), (QUERY, "receive"): ("reply", "declare_queryable"),
    (TOKEN, "send"): (), (TOKEN, "receive"): ("liveliness_token", "reply"),
}
ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")


class AuthError(ValueError):
    """An auth folder that is missing, incomplete, or has no credential for a role."""


def env_auth() -> Path | None:
    """The auth folder of env NASA_ZENOH_AUTH, or None (no authentication)."""
    value = os.environ.get("NASA_ZENOH_AUTH", "")
    return Path(value) if value else None


def acl(wiring: tuple[Route, ...] | None = None) -> dict:
    """The router's access_control section: deny by default; per role, allow its side of each route."""
    grants: dict[tuple[str, str, tuple[str, ...]], list[str]] = defaultdict(list)
    for route in wiring if wiring is not None else routes():
        for side, roles in (("send", route.senders), ("receive", route.receivers)):
            for role in roles:
                for flow, table in (("ingress", _INGRESS), ("egress", _EGRESS)):
                    if messages := table[(route.kind, side)]:
                        grants[(role, flow, messages)].append(route.key)
    rules = [{"id": f"{role}-{flow}-{i}", "messages": list(messages), "flows": [flow], "permission": "allow",
              "key_exprs": sorted(set(keys))}
             for i, ((role, flow, messages), keys) in enumerate(sorted(grants.items()))]
    # Routers of several sites forward each other's traffic whatever it is.
    rules.append({"id": "router-all", "messages": list(ALL_MESSAGES), "flows": ["ingress", "egress"],
                  "permission": "allow", "key_exprs": ["nasa/**"]})
    # A router that joins this one logs in; the one this router joins presents only its TLS
    # certificate (common name `router`, shared/zenoh_tls.py), so routers are known by either.
    subjects = [{"id": role, "usernames": [role]} for role in AUTH_ROLES]
    subjects.append({"id": f"{ROUTER}-cert", "cert_common_names": [ROUTER]})
    policies = [{"id": f"{role}-policy", "subjects": [role, f"{ROUTER}-cert"] if role == ROUTER else [role],
                 "rules": [r["id"] for r in rules if r["id"].startswith(f"{role}-")]} for role in AUTH_ROLES]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": [p for p in policies if p["rules"]]}


def init(folder: Path, run_id: str = ANY, force: bool = False) -> Path:
    """Write new credentials (users.txt, 0600) and the ACL for run `run_id` (every run: ANY) to `folder`.
    An existing users.txt is kept unless `force` (rotation: write new ones, restart every process)."""
    routes(run_id)  # first: a bad run id leaves no folder
    folder.mkdir(parents=True, exist_ok=True)
    users = folder / USERS_FILE
    if users.exists() and not force:
        raise FileExistsError(f"{users} exists: pass --force to replace every credential")
    lines = "".join(f"{role}:{secrets.token_urlsafe(24)}\n" for role in AUTH_ROLES)
    tmp = users.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    # O_CREAT's mode applies to a new file only: a users.tmp left by a crash keeps its own.
    os.fchmod(fd, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(lines)
    os.replace(tmp, users)
    write_acl(folder, run_id)
    return folder


def write_acl(folder: Path, run_id: str = ANY) -> None:
    """(Re)write `folder`/acl.json for run `run_id` from today's wiring; the credentials stay."""
    path = folder / ACL_FILE
    replace_text(path, json.dumps(acl(routes(run_id)), indent=1) + "\n", tmp=path.with_suffix(".tmp"))


def check_acl(folder: Path, run_id: str | None = None) -> None:
    """AuthError unless the folder's acl.json is the one `init` makes today for `run_id` or every run:
    an ACL for another run, or from an older wiring, would deny this run's messages without a word.
    `run_id` None (a router not told its run: no NASA_RUN_ID): for any run it names."""
    path = folder / ACL_FILE
    text = _read(path, folder) if path.exists() else "null"
    try:
        held = json.loads(text)
    except ValueError:  # a damaged one: made anew by the same command
        held = None
    named = sorted(_runs_named(held))
    runs = [ANY, run_id] if run_id is not None else [ANY, *named]
    # A missing or damaged file (None) matches no ACL, not even the None of a run id no run can have.
    if held is None or not any(held == _acl_of(run) for run in runs):
        run = run_id or (named[0] if len(named) == 1 else "RUN_ID")
        remake = f"`nasa auth init {folder} --run-id {run} --acl-only` makes it anew and keeps the passwords"
        if run_id is not None and len(named) == 1 and held == _acl_of(named[0]):
            raise AuthError(f"{path} is made for run {named[0]}, not {run_id}: {remake}")
        raise AuthError(f"{path} is missing, or made for another run or an older wiring: {remake}")


def _acl_of(run_id: str) -> dict | None:
    """The ACL `init` makes today for `run_id`; None for a name no run can have."""
    try:
        return acl(routes(run_id))
    except ValueError:
        return None


def _runs_named(held: object) -> set[str]:
    """The runs whose stop key (`nasa/<run_id>/control/stop`) an ACL's rules name, wildcards left out."""
    rules = held.get("rules") if isinstance(held, dict) else None
    runs: set[str] = set()
    for rule in rules if isinstance(rules, list) else []:
        exprs = rule.get("key_exprs") if isinstance(rule, dict) else None
        for expr in exprs if isinstance(exprs, list) else []:  # a hand-edited file may hold anything
            parts = str(expr).split("/")
            if parts[0] == PREFIX and parts[2:] == ["control", "stop"] and parts[1] != ANY:
                runs.add(parts[1])
    return runs


def _read(path: Path, folder: Path) -> str:
    """The text of one of the auth folder's files; AuthError (one line) if it cannot be read."""
    if not path.exists():
        raise AuthError(f"no {path}: make the auth folder with `nasa auth init {folder}`")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:  # a folder in its place, not this user's, garbled
        raise AuthError(f"cannot read {path} ({err.__class__.__name__}: {err}): check its owner and mode, "
                        f"or make it anew with `nasa auth init {folder} --force`") from err


def credentials(folder: Path) -> dict[str, str]:
    """role -> password, from `folder`/users.txt."""
    path = folder / USERS_FILE
    out = {}
    for line in _read(path, folder).splitlines():
        user, sep, password = line.strip().partition(":")
        if sep and user and password:
            out[user] = password
    return out


def apply_client(config: zenoh.Config, folder: Path, role: str) -> None:
    """Log in as `role` with its password from the auth folder."""
    password = credentials(folder).get(role)
    if password is None:
        raise AuthError(f"{folder / USERS_FILE} holds no credential for role {role!r}")
    config.insert_json5("transport/auth/usrpwd", json.dumps({"user": role, "password": password}))


def apply_router(config: zenoh.Config, folder: Path) -> None:
    """Require a login from the dictionary and enforce the folder's ACL."""
    users, rules = folder / USERS_FILE, folder / ACL_FILE
    known = credentials(folder)
    # Zenoh turns logins off for an empty dictionary: every client would get in unnamed.
    if missing := [role for role in ROLES if role not in known]:
        raise AuthError(f"{users} holds no credential for {', '.join(missing)}: a router needs every "
                        f"role's; `nasa auth init {folder} --force` writes them all")
    text = _read(rules, folder)
    try:
        json.loads(text)
    except ValueError as err:  # else Zenoh's multi-line parse error, as if the port were at fault
        raise AuthError(f"{rules} is not JSON ({err}): "
                        f"`nasa auth init {folder} --force` makes it anew") from err
    usrpwd: dict[str, str] = {"dictionary_file": str(users.resolve())}
    if ROUTER in known:  # what this router presents when it connects to another site's
        usrpwd |= {"user": ROUTER, "password": known[ROUTER]}
    config.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    config.insert_json5("access_control", text)
