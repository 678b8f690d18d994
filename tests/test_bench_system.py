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


def test_a_device_that_is_not_here_is_refused_before_anything_runs(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--device", "cuda:7"])
    assert exit_.value.code == 2 and "--device: " in capsys.readouterr().err


def test_a_service_that_ends_is_named_at_once_not_waited_on(tmp_path):
    # A replay that refuses its flags: the wait for inserts says so instead of lasting its timeout.
    import argparse
    import time

    from bench.system import Cluster

    cluster = Cluster(argparse.Namespace(task="cartpole-balance", algo="nasa_td3"), tmp_path)
    try:
        cluster.start("replay", "replay", ["--no-such-flag"])
        start = time.monotonic()
        with pytest.raises(RuntimeError, match=r"replay exited with 2 \(.*replay\.log: .*no-such-flag"):
            cluster.insert_rate(1.0, timeout=120.0)
        assert time.monotonic() - start < 100
    finally:
        cluster.close()


def test_a_window_shorter_than_the_replays_stats_interval_waits_for_the_next_stats(tmp_path):
    import threading

    from bench.system import Cluster

    cluster = Cluster.__new__(Cluster)  # the rate's arithmetic alone: stats as the replay sends them
    cluster.inserted, cluster.data, cluster.check_alive = [(1.0, 10)], tmp_path, lambda: None
    late = threading.Timer(0.3, lambda: cluster.inserted.append((2.0, 30)))
    late.start()
    rate, cpu = cluster.insert_rate(0.01, settle_s=0.0)
    late.join()
    assert rate == 20.0 and set(cpu) == {"router"}
