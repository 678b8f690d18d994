"""Which client a bridge serves: one gripper, one client at a time.

Two clients on one bridge (two actors pointed at one id by hand, a second launch) would take
turns resetting the gripper, each refusing the other's next step as stale, and neither would
record anything. So the bridge holds the gripper for the client it last served and refuses
every other until the holder has been silent for `hold_s`; then the next client to reset takes
it. A client is named without its pid, so the same actor restarted on its host (`nasa up`
restarts it with its id) gets the gripper back at once.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from shared.text import clip

DEFAULT_HOLD_S = 35.0
"""A little more than a client's request timeout (`BridgeEnv`'s 30 s): a holder whose request
was lost on the way (a router cut off) waits that long before it asks again, and is still there."""


# A name is cut in refusals and the log: a refusal quoting one of any length the wire takes would
# be longer than the client reads (wire.MAX_TEXT), and read as a malformed reply, not as held.
CLIENT_CHARS = 256


def who(client: str, pid: int) -> str:
    """A client as a refusal or the log names it: its name, and its pid where it sent one."""
    name = clip(client, CLIENT_CHARS)
    return f"{name} (pid {pid})" if pid else name


class ClientHold:
    """The client the bridge serves, and when it was last heard from."""

    def __init__(self, hold_s: float, log: Callable[[str], None]) -> None:
        self.hold_s = hold_s
        self.log = log
        self.client: str | None = None
        self.pid = 0
        self.heard = 0.0

    def refusal(self, client: str, pid: int, takes: bool) -> str | None:
        """Why `client` may not use the gripper now, or None: it holds it (heard now), or it
        `takes` it (a reset) from a holder silent for `hold_s` or more."""
        now = time.monotonic()
        if self.client is not None and client != self.client:
            silent = now - self.heard
            if not takes or silent < self.hold_s:
                return (f"the gripper is held by {self.holder()}, last heard {silent:.1f} s ago; "
                        f"another client may take it after {self.hold_s:g} s of silence from it")
            self.log(f"gripper handed over from {self.holder()} (silent for {silent:.1f} s) "
                     f"to {who(client, pid)}")
        elif self.client is None:
            self.log(f"gripper held by {who(client, pid)}")
        self.client, self.pid, self.heard = client, pid, now
        return None

    def holder(self) -> str:
        """The holder as a refusal names it ("" before the first client)."""
        return who(self.client, self.pid) if self.client is not None else ""
