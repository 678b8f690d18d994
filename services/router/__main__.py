"""`python -m services.router --help`: run a Zenoh router until SIGINT/SIGTERM.

`nasa up` runs the same router inside its own process; deployments run this
module (or the zenohd binary) as the `router` service.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import tyro

from shared.service import Log, StopFlag, die_with_parent
from shared.zenoh_session import open_router


@dataclass
class RouterArgs:
    """A Zenoh router every service of a run connects to."""

    listen: str = field(default_factory=lambda: os.environ.get("NASA_ZENOH_LISTEN", "tcp/127.0.0.1:7447"))
    """Endpoint to listen on (env NASA_ZENOH_LISTEN), e.g. tcp/0.0.0.0:7447 in a container."""


def main(argv: list[str] | None = None) -> None:
    die_with_parent()
    args = tyro.cli(RouterArgs, args=argv, prog="python -m services.router")
    stop = StopFlag()
    stop.install_signal_handlers()
    log = Log("router")
    with open_router(args.listen):
        log(f"listening on {args.listen}")
        stop.wait()
        log(f"stopping ({stop.reason})")


if __name__ == "__main__":
    main()
