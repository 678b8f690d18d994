"""Actors on another host: two network namespaces joined by a veth pair, the actors reaching the
router over TLS with their own logins, and a cut link survived with nothing acknowledged lost."""

from __future__ import annotations

import time

import pytest
from netns_harness import SplitSystem, TwoHosts, unavailable

pytestmark = [pytest.mark.system, pytest.mark.timeout(420)]

# Longer than Zenoh's lease: the sessions over the link do drop, the actors see the replay go,
# and everything reconnects when the link is back (the harder case than a blip TCP rides out).
CUT_S = 15.0


@pytest.fixture
def hosts():
    reason = unavailable()
    if reason is not None:
        pytest.skip(f"no network namespaces here: {reason}")
    two = TwoHosts()
    try:
        yield two
    finally:
        two.close()


@pytest.mark.parametrize("site_router", [False, True], ids=["one-router", "router-per-site"])
def test_actors_on_another_host_join_over_tls_and_survive_a_cut_link(hosts: TwoHosts, tmp_path,
                                                                     site_router: bool) -> None:
    """One router for both hosts, or a router per host joined to the other over TLS."""
    system = SplitSystem(hosts, tmp_path / "run", actors=2, secure=True, site_router=site_router)
    sizes: list[int] = []

    def record(s: dict) -> None:
        sizes.append(s["replay"]["size"])

    try:
        before = system.wait_for(
            "both actors on host B alive over the link, and the learner updating",
            lambda s: len(s["actors"]) == 2 and all(a["alive"] and a["env_steps"] > 0 for a in s["actors"])
            and s["updates"] > 0, seen=record)
        steps = {a["id"]: a["env_steps"] for a in before["actors"]}

        hosts.link(up=False)
        cut_until = time.monotonic() + CUT_S
        while time.monotonic() < cut_until:  # the learner goes on with what the replay holds
            if (s := system.status()) is not None:
                record(s)
            time.sleep(0.5)
        hosts.link(up=True)

        logs = tmp_path / "run" / "logs"

        def actor_log() -> str:
            return "".join(f.read_text() for f in logs.glob("actor-*.log"))

        system.wait_for("both actors to see the replay go and come back",
                        lambda s: actor_log().count("the replay is back") == 2, seen=record)
        assert actor_log().count("the replay is gone") == 2
        back = system.wait_for("a status after the link came back", lambda s: True, seen=record)
        steps = {a["id"]: a["env_steps"] for a in back["actors"]}
        after = system.wait_for(
            "both actors storing experience again after the link came back",
            lambda s: all(a["alive"] and a["env_steps"] > steps[a["id"]] + 10 for a in s["actors"])
            and s["replay"]["size"] > back["replay"]["size"] + 40 and s["updates"] > back["updates"],
            seen=record)
        # Nothing acknowledged is lost: the replay's size (acknowledged transitions only) never went down.
        assert all(b >= a for a, b in zip(sizes, sizes[1:], strict=False)), sizes
        assert len(after["actors"]) == 2
        assert system.restarts() == {name: 0 for name in system.restarts()}, system.logs()
        assert "no acknowledgement for 60 s" not in actor_log()
    finally:
        system.close()
