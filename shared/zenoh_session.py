"""Opening Zenoh sessions from flags and environment variables.

Services connect as clients to a router (`NASA_ZENOH_CONNECT`, e.g.
tcp/127.0.0.1:7447); `nasa up` and `python -m services.router` run that
router. Multicast scouting is off: a service talks only to the router it is
told about, so runs on one host never find each other by accident.
With an auth folder (NASA_ZENOH_AUTH, shared/zenoh_auth.py) clients log in as their role and the
router checks logins and its access-control list; without one nothing changes. A tls/ endpoint
also encrypts the link, with the folder's certificates (shared/zenoh_tls.py).
Use the returned session as a context manager: a process holding a callback
subscriber hangs at exit unless its session is closed.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
import zenoh

from shared import zenoh_auth, zenoh_tls
from shared.config import DEFAULT_PRESET, TrainConfig

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def env_connect() -> str:
    return os.environ.get("NASA_ZENOH_CONNECT", DEFAULT_CONNECT)


def env_run_id() -> str:
    return os.environ.get("NASA_RUN_ID", "default")


def env_int(name: str, default: int) -> int:
    """An integer flag's default from environment variable `name` (unset or empty: `default`). One
    that is no integer is a ConfigError (exit 2, one line), not a traceback its supervisor restarts."""
    from shared.config import ConfigError

    value = os.environ.get(name)
    if not value:
        return default
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f"{name}={value!r} is not an integer") from None


def _base_config(mode: str) -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


class RouterUnreachable(zenoh.ZError):
    """No router accepted this session in time. A zenoh.ZError, so callers that retry on one still
    do; a service's main names it in one line and exits non-zero, for its supervisor to retry."""


class SessionRefused(RouterUnreachable):
    """The router's port is open but no session opened: a refused login or TLS certificate, most
    likely. Still retried (the router may be restarted with the folder it should have)."""


def _listening(endpoint: str, timeout_s: float = 1.0) -> bool:
    """Whether a tcp/ or tls/ endpoint's host:port accepts a TCP connection."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("?")[0].split("#")[0].rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit():
        return False
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def open_client(connect: str, timeout_s: float = 30.0, role: str | None = None,
                auth: Path | None = None) -> zenoh.Session:
    """A client session to the router(s) in `connect` (comma-separated endpoints), retried until up.

    With an auth folder (`auth`, else env NASA_ZENOH_AUTH) it logs in as `role`; a router that
    refuses the login raises SessionRefused (a RouterUnreachable) after `timeout_s`."""
    endpoints = [e.strip() for e in connect.split(",") if e.strip()]
    if not endpoints:
        raise ValueError("no Zenoh endpoint to connect to (set --connect or NASA_ZENOH_CONNECT)")
    config = _base_config("client")
    config.insert_json5("connect/endpoints", json.dumps(endpoints))
    folder = auth or zenoh_auth.env_auth()
    tls = zenoh_tls.is_tls(endpoints)
    if tls and folder is None:
        raise zenoh_auth.AuthError(f"{connect} is a TLS link: it needs the run's auth folder with its "
                                   "certificates (NASA_ZENOH_AUTH; `nasa auth tls DIR --host HOST`)")
    if folder is not None:
        if role is None:
            raise zenoh_auth.AuthError(f"an auth folder ({folder}) is set, but this session has no role")
        zenoh_auth.apply_client(config, folder, role)
        if tls:
            zenoh_tls.apply_client(config, folder, role)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(config)
        except zenoh.ZError as err:
            if time.monotonic() >= deadline:
                # Zenoh's error is the same for a refused login as for no router: tell them apart,
                # else a wrong password reads as a network fault for ever.
                if up := [e for e in endpoints if _listening(e)]:
                    who = (f"{role!r}'s login from {folder} (a password its users.txt lacks: rotated "
                           "without restarting it?)" if folder is not None else "a session without a login")
                    raise SessionRefused(
                        f"the Zenoh router at {', '.join(up)} is up but refused {who}"
                        + (" or this role's TLS certificate" if tls else "") + f": {err}") from err
                login = f"; or it refused {role!r}'s login from {folder}" if folder is not None else ""
                raise RouterUnreachable(
                    f"no Zenoh router answered at {connect} within {timeout_s:g} s (is it up? `nasa up` "
                    f"starts one; alone: python -m services.router{login}): {err}"
                ) from err
            time.sleep(0.2)


def token_up(session: zenoh.Session, key: str, timeout_s: float = 2.0) -> bool:
    """Whether a liveliness token matching `key` is up, as this session sees it through the router."""
    return any(r.ok is not None for r in session.liveliness().get(key, timeout=timeout_s))


def open_router(listen: str, auth: Path | None = None, join: str = "") -> zenoh.Session:
    """A session in router mode listening on `listen` (e.g. tcp/127.0.0.1:7447): the run's router.
    With an auth folder it accepts only the logins of its users.txt and enforces its acl.json; on a
    tls/ endpoint it also requires a client certificate from the folder's CA (shared/zenoh_tls.py).
    `join`: other routers' endpoints (comma-separated; a router per site), connected to and
    reconnected to after a link loss, logged in as the `router` role."""
    config = _base_config("router")
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    peers = [e.strip() for e in join.split(",") if e.strip()]
    if peers:
        config.insert_json5("connect/endpoints", json.dumps(peers))
    # A site's router may listen in plain TCP for its own host and join the others over TLS.
    if tls := [e for e in (listen, *peers) if zenoh_tls.is_tls([e])]:
        if auth is None:
            raise zenoh_auth.AuthError(f"{', '.join(tls)}: a TLS link needs an auth folder with the "
                                       "run's certificates (`nasa auth tls DIR --host HOST`)")
        zenoh_tls.apply_router(config, auth)
    if auth is not None:
        zenoh_auth.apply_router(config, auth)
    return zenoh.open(config)


@dataclass
class ServiceArgs:
    """The flags every service of a run takes: the run's config and where the router is."""

    config: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=TrainConfig)
    preset: str = DEFAULT_PRESET
    """`paper`, `cpu-small`, or `auto` (paper on a GPU, cpu-small on a CPU)."""
    run_config: Path | None = None
    """The run's config.json (`nasa up` passes it): its settings are this service's; config
    flags given as well must agree with it."""
    connect: str = field(default_factory=env_connect)
    """Zenoh router endpoint(s), comma-separated (env NASA_ZENOH_CONNECT)."""
    run_id: str = field(default_factory=env_run_id)
    """Run id: the key prefix nasa/<run_id>/ (env NASA_RUN_ID)."""
