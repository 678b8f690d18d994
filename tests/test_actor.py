"""The actor's reported env-step rate."""

from services.actor.actor import StepRate


def test_step_rate_spans_backpressure_pauses_and_forgets_old_progress():
    rate = StepRate(start=0.0, window_s=10.0)
    for t in range(1, 6):  # 8 steps/s for 5 s
        assert rate.update(float(t), 8 * t) == 8.0
    # Held back by the replay for 3 s: the rate drops but does not read 0.
    assert rate.update(8.0, 40) == 5.0
    # Still paused 10 s later: nothing happened within the window.
    assert rate.update(18.0, 40) == 0.0
    assert rate.update(19.0, 46) == 6.0 / 11.0  # the window starts at the newest point >= 10 s old


def test_an_actor_id_the_replay_cannot_take_exits_2_with_the_reason_before_it_connects():
    """An id the replay refuses (negative, or past 32 bits) left the actor acting with every episode
    refused; a NASA_ACTOR_ID that is no integer was a traceback (exit 1, restarted in a loop)."""
    import os
    import subprocess
    import sys

    from nasa.up import free_port

    # No router listens there: the id, not the connection, must be the error.
    base = {**os.environ, "NASA_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}", "NASA_RUN_ID": "bad"}
    base.pop("NASA_ACTOR_ID", None)
    for flags, env, reason in (([], {"NASA_ACTOR_ID": "abc"}, "NASA_ACTOR_ID='abc' is not an actor id"),
                               (["--actor-id", "-2"], {}, "--actor-id must be -1"),
                               (["--actor-id", str(2**31)], {}, "--actor-id must be -1")):
        proc = subprocess.run([sys.executable, "-m", "services.actor", *flags], env={**base, **env},
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert reason in proc.stderr and "Traceback" not in proc.stderr
