"""bench.system's router round trip runs on the run's own keys and roles, with logins and the ACL
on (so the ACL lets an actor's insert and the replay's acknowledgement through) and off."""

from __future__ import annotations

import pytest

from bench.system import main, router_round_trip


@pytest.mark.parametrize("auth", [False, True])
def test_router_round_trip_completes(auth):
    wall_us, cpu_us = router_round_trip(auth, seconds=0.3, payload_bytes=4096)
    assert 0 < wall_us < 1e6
    assert cpu_us >= 0


def test_only_auth_needs_rounds(capsys):
    with pytest.raises(SystemExit):
        main(["--only-auth"])
    assert "--only-auth needs --auth-rounds" in capsys.readouterr().err
