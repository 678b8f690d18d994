"""`python -m services.router --help`: run a Zenoh router until SIGINT/SIGTERM.

`nasa up` runs the same router inside its own process; deployments run this
module (or the zenohd binary) as the `router` service.

Given an auth folder, it refuses (exit 2) an ACL that is not today's: from an older wiring, or,
where NASA_RUN_ID names its run (k8s and compose set it), made for another run. A NASA_RUN_ID
that is no run id is refused (exit 2) before anything is opened.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from shared.service import EXIT_BAD_INPUT, FlagError, Log, StopFlag, die_with_parent, read_flags
from shared.wire import check_run_id
from shared.zenoh_auth import USERS_FILE, AuthError, check_acl, env_auth
from shared.zenoh_session import open_router


@dataclass
class RouterArgs:
    """A Zenoh router every service of a run connects to."""

    listen: str = field(default_factory=lambda: os.environ.get("NASA_ZENOH_LISTEN", "tcp/127.0.0.1:7447"))
    """Endpoint to listen on (env NASA_ZENOH_LISTEN), e.g. tcp/0.0.0.0:7447 in a container."""
    join: str = field(default_factory=lambda: os.environ.get("NASA_ZENOH_JOIN", ""))
    """Other routers to join, comma-separated (env NASA_ZENOH_JOIN): a router per site, the sites'
    routers joined. Each site's services connect to their own router; a lost link to another site
    is retried until it is back."""
    auth: Path | None = field(default_factory=env_auth)
    """Auth folder (`nasa auth init DIR`; env NASA_ZENOH_AUTH): require each role's login and enforce
    its access-control list. None: no authentication."""


def main(argv: list[str] | None = None) -> None:
    die_with_parent()
    try:
        args = read_flags(RouterArgs, sys.argv[1:] if argv is None else argv, "python -m services.router")
    except FlagError as err:
        print(f"router: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    # Told its run (NASA_RUN_ID, as k8s and compose set it), the router takes only that run's ACL
    # or every run's: another run's would deny each of this run's services without a word.
    run_id = os.environ.get("NASA_RUN_ID") or None
    if run_id is not None:
        try:
            check_run_id(run_id)  # else the ACL's refusal would name a command that refuses it too
        except ValueError as err:
            print(f"router: error: NASA_RUN_ID: {err}", file=sys.stderr, flush=True)
            sys.exit(EXIT_BAD_INPUT)
    stop = StopFlag()
    stop.install_signal_handlers()
    log = Log("router")
    try:
        if args.auth is not None:
            # Zenoh enforces whatever acl.json holds: one from an older wiring would drop the newer
            # keys' messages (an e-stop's answer) without a word, so it is refused here, naming the fix.
            check_acl(args.auth, run_id)
        router = open_router(args.listen, auth=args.auth, join=args.join)
    except AuthError as err:
        print(f"router: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    except zenoh.ZError as err:  # a busy port, an endpoint that does not parse: the same again
        print(f"router: error: cannot listen on {args.listen}: {str(err).strip().splitlines()[0]}",
              file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    with router:
        if args.auth is not None and (args.auth / USERS_FILE).stat().st_mode & 0o004:
            # Anyone on the host could log in as any role: say so (a mount may not allow a chmod).
            log(f"warning: {args.auth / USERS_FILE} is readable by every user of this host: "
                f"chmod 600 it (or 640 for the router's group)")
        log(f"listening on {args.listen}" + (f", joining {args.join}" if args.join else "")
            + (f"; logins and ACL from {args.auth}" if args.auth else ""))
        stop.wait()
        log(f"stopping ({stop.reason})")
    stop.exit_if_signalled()


if __name__ == "__main__":
    main()
