"""`nasa auth init DIR`: the Zenoh credentials of every role and the router's access-control list;
`nasa auth tls DIR --host H`: the certificates for TLS links to a router reachable as H."""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, NoReturn

import tyro

from shared import zenoh_auth, zenoh_tls
from shared.service import read_flags
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
    acl_only: bool = False
    """Rewrite only DIR/acl.json, from this version's keys, and keep the passwords: for a folder
    whose ACL a newer version refuses as made for an older wiring (restart the router afterwards)."""


@dataclass
class AuthTls:
    """Write DIR/tls/: a CA for the run, the router's certificate for the given hosts, and one client
    certificate per role. Then listen and connect on tls/HOST:PORT endpoints: the router accepts
    only clients holding a certificate from this CA, and clients check the router's."""

    folder: tyro.conf.Positional[Path]
    # Appended: without it tyro keeps only the last of repeated flags, and a router named by an
    # earlier --host would be missing from its certificate.
    host: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """A name or address clients reach the router by (repeat the flag for each); localhost and
    127.0.0.1 are always included."""
    force: bool = False
    """Issue every certificate anew (restart the router and every service afterwards)."""


USAGE = ("usage: nasa auth init DIR [--run-id ID] [--force | --acl-only]\n"
         "       nasa auth tls DIR --host HOST [--host ...] [--force]")


def auth(argv: list[str]) -> None:
    if not argv or argv[0] not in ("init", "tls"):
        asked = bool(argv) and argv[0] in ("-h", "--help")
        if argv and not asked:
            print(f"nasa auth: unknown command {argv[0]!r}", file=sys.stderr)
        print(USAGE, file=sys.stdout if asked else sys.stderr)  # as `nasa --help` and `nasa trian`
        sys.exit(0 if asked else 2)
    if argv[0] == "tls":
        tls(argv[1:])
        return
    cmd = read_flags(AuthInit, argv[1:], "nasa auth init")
    if cmd.acl_only:
        if cmd.force:
            _fail("--acl-only keeps the passwords and --force replaces them: pass one of the two")
        if not (cmd.folder / zenoh_auth.USERS_FILE).exists():
            _fail(f"no {cmd.folder / zenoh_auth.USERS_FILE}: --acl-only rewrites the ACL of a folder "
                  f"made before; make one with `nasa auth init {cmd.folder}`")
        write(cmd.folder, lambda: zenoh_auth.write_acl(cmd.folder, cmd.run_id) or cmd.folder)
        print(f"nasa auth: ACL for run {cmd.run_id!r} in {cmd.folder / zenoh_auth.ACL_FILE}; "
              f"the passwords in {cmd.folder / zenoh_auth.USERS_FILE} are kept", flush=True)
        return
    folder = write(cmd.folder, lambda: zenoh_auth.init(cmd.folder, cmd.run_id, cmd.force))
    roles = ", ".join(zenoh_auth.AUTH_ROLES)
    print(f"nasa auth: credentials for {roles} in {folder / zenoh_auth.USERS_FILE} (0600); "
          f"ACL for run {cmd.run_id!r} in {folder / zenoh_auth.ACL_FILE}", flush=True)


def tls(argv: list[str]) -> None:
    cmd = read_flags(AuthTls, argv, "nasa auth tls")
    out = write(cmd.folder, lambda: zenoh_tls.init(cmd.folder, list(cmd.host), cmd.force))
    hosts = ", ".join((out / "hosts.txt").read_text().split())
    print(f"nasa auth: a CA, the router's certificate (for {hosts}) and one client certificate per role "
          f"in {out} (keys 0600)", flush=True)


def write(folder: Path, make: Callable[[], Path]) -> Path:
    """Run `make` (it writes into `folder`); bad input or a folder it cannot write is one line, exit 2."""
    if folder.exists() and not folder.is_dir():
        _fail(f"{folder} is a file, not a folder: name a folder to write the credentials in")
    try:
        return make()
    except (ValueError, FileExistsError) as err:  # a bad run id or host (AuthError); no --force
        _fail(str(err))
    except OSError as err:  # under a file, not writable, a full disk
        _fail(f"cannot write {folder}: {err}")


def _fail(message: str) -> NoReturn:
    print(f"nasa auth: error: {message}", file=sys.stderr)
    sys.exit(2)
