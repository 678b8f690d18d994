"""`nasa auth init DIR`: the Zenoh credentials of every role and the router's access-control list."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from shared import zenoh_auth
from shared.wire import ANY


@dataclass
class AuthInit:
    """Write DIR/users.txt (one random password per role, mode 0600) and DIR/acl.json (each role's
    keys, from shared/wire.py). Point the router and every service at DIR (env NASA_ZENOH_AUTH)."""

    folder: tyro.conf.Positional[Path]
    run_id: str = ANY
    """Limit the ACL to this run's keys (default `*`: every run on the router)."""
    force: bool = False
    """Replace existing credentials (rotation: restart the router and every service afterwards)."""


def auth(argv: list[str]) -> None:
    if not argv or argv[0] != "init":
        print("usage: nasa auth init DIR [--run-id ID] [--force]", file=sys.stderr)
        sys.exit(0 if argv and argv[0] in ("-h", "--help") else 2)
    cmd = tyro.cli(AuthInit, args=argv[1:], prog="nasa auth init")
    try:
        folder = zenoh_auth.init(cmd.folder, cmd.run_id, cmd.force)
    except ValueError as err:  # a run id that cannot be a key prefix
        print(f"nasa auth: error: {err}", file=sys.stderr)
        sys.exit(2)
    roles = ", ".join(zenoh_auth.AUTH_ROLES)
    print(f"nasa auth: credentials for {roles} in {folder / zenoh_auth.USERS_FILE} (0600); "
          f"ACL for run {cmd.run_id!r} in {folder / zenoh_auth.ACL_FILE}", flush=True)
