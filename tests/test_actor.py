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
