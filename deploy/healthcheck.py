"""Container health checks, one per role: `python healthcheck.py ROLE`, exit 0 when healthy.

    learner   GET /healthz of its status API (NASA_STATUS_HOST, NASA_STATUS_PORT; default
              127.0.0.1:8000) answers 200 "ok", or
              200 "degraded: ..." (it trains on past writes the disk refuses; the reason is printed)
    router    its Zenoh port (from NASA_ZENOH_LISTEN, default 7447) accepts a connection
    replay    its liveliness token is visible through the router (NASA_ZENOH_CONNECT, NASA_RUN_ID)
    actor, evaluator
              the router they are told about (NASA_ZENOH_CONNECT) accepts a connection
    robot_bridge
              its liveliness token (bridge NASA_BRIDGE_ID) is visible through the router

The image's HEALTHCHECK runs the learner's; the compose file and the Kubernetes manifests run
the one of each service's role.
"""

from __future__ import annotations

import os
import re
import socket
import sys
import urllib.request

TIMEOUT_S = 4.0


def _host_port(endpoint: str, default_port: int) -> tuple[str, int]:
    # proto/host:port?metadata#config (Zenoh's endpoint syntax); the first of a comma-separated list.
    # The metadata and config name no part of the address.
    address = endpoint.split(",")[0].strip().split("/", 1)[-1]
    address = re.split(r"[?#]", address, maxsplit=1)[0]
    host, _, port = address.rpartition(":")
    return (host or "127.0.0.1").strip("[]"), int(port or default_port)


def tcp_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=TIMEOUT_S):
            return True
    except OSError:
        return False


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args: object, **kwargs: object) -> None:
        return None  # the 3xx itself is the answer: an HTTPError, so unhealthy


def learner() -> bool:
    """The learner's /healthz answers 200 "ok" itself: a redirect (to a page that answers 200) or
    another server's 200 on the port is not the learner being healthy."""
    port = int(os.environ.get("NASA_STATUS_PORT", "8000"))
    host = os.environ.get("NASA_STATUS_HOST", "127.0.0.1").strip("[]")
    # Listening on every interface: loopback is one of them; on one address: only that one.
    host = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    opener = urllib.request.build_opener(_NoRedirect)
    try:
        url_host = f"[{host}]" if ":" in host else host
        with opener.open(f"http://{url_host}:{port}/healthz", timeout=TIMEOUT_S) as response:
            body = response.read(4096)
    except OSError:
        return False
    if response.status == 200 and body.startswith(b"degraded"):
        # Healthy to the orchestrator: a restart would meet the same disk and lose the updates
        # since the last checkpoint. Said, so the container's health log shows it.
        print(body.decode("utf-8", "replace").strip())
        return True
    return response.status == 200 and body.startswith(b"ok")


def router() -> bool:
    host, port = _host_port(os.environ.get("NASA_ZENOH_LISTEN", "tcp/0.0.0.0:7447"), 7447)
    # Listening on every interface: loopback is one of them; on one address: only that one.
    return tcp_open("127.0.0.1" if host in ("0.0.0.0", "::", "") else host, port)


def _token_seen(key: str, role: str) -> bool:
    """Whether the liveliness token `key` is visible through the router, logged in as `role`."""
    from shared.zenoh_session import env_connect, open_client, token_up

    with open_client(env_connect(), timeout_s=TIMEOUT_S, role=role) as session:
        return token_up(session, key, TIMEOUT_S)


def replay() -> bool:
    from shared.wire import Keys
    from shared.zenoh_session import env_run_id

    return _token_seen(Keys(env_run_id()).alive("replay", 0), role="replay")


def robot_bridge() -> bool:
    from shared.wire import BridgeKeys

    # Logged in as an actor: the role that watches a bridge's token.
    return _token_seen(BridgeKeys(os.environ["NASA_BRIDGE_ID"]).alive, role="actor")


def reaches_router() -> bool:
    return tcp_open(*_host_port(os.environ.get("NASA_ZENOH_CONNECT", "tcp/127.0.0.1:7447"), 7447))


CHECKS = {"learner": learner, "router": router, "replay": replay, "actor": reaches_router,
          "evaluator": reaches_router, "robot_bridge": robot_bridge}


def main(argv: list[str]) -> int:
    if len(argv) != 1 or argv[0] not in CHECKS:
        print(f"usage: healthcheck.py {{{','.join(CHECKS)}}}", file=sys.stderr)
        return 2
    try:
        healthy = CHECKS[argv[0]]()
    except Exception as err:  # noqa: BLE001 (any failure to check is "unhealthy", with its reason)
        print(f"healthcheck {argv[0]}: {err}", file=sys.stderr)
        return 1
    print(f"healthcheck {argv[0]}: {'ok' if healthy else 'unhealthy'}")
    return 0 if healthy else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
