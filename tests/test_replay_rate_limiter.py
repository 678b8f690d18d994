"""SampleToInsertRatio: blocks whichever side runs ahead, releases it, never deadlocks."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from shared.replay import RateLimiterClosed, SampleToInsertRatio


class Watched(SampleToInsertRatio):
    """Records the threads whose wait it has refused. It checks and waits under one lock, so a
    thread recorded here is in its wait by the time another can change the limiter."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self.refused: set[int] = set()

    def can_insert(self, n: int = 1) -> bool:
        ok = super().can_insert(n)
        if not ok:
            self.refused.add(threading.get_ident())
        return ok

    def can_sample(self, n: int = 1) -> bool:
        ok = super().can_sample(n)
        if not ok:
            self.refused.add(threading.get_ident())
        return ok


def wait_blocked(threads: list[threading.Thread], *limiters: Watched) -> None:
    """Until every thread waits in one of the limiters; the deadline only stops a hung test."""
    deadline = time.monotonic() + 10
    while not all(any(t.ident in rl.refused for rl in limiters) for t in threads):
        assert time.monotonic() < deadline, "a thread never waited"
        time.sleep(0.01)


def test_min_size_blocks_samples_not_inserts() -> None:
    rl = SampleToInsertRatio(samples_per_insert=2.0, min_size_to_sample=3, error_buffer=2.0)
    assert not rl.take_sample(timeout=0.01)
    for _ in range(3):
        assert rl.await_insert(timeout=0.01)
        rl.insert()
    assert rl.take_sample(timeout=0.01)


def test_inserts_block_when_ahead_and_release_on_sample() -> None:
    rl = Watched(samples_per_insert=2.0, min_size_to_sample=1, error_buffer=2.0)
    rl.insert()  # diff = 2 = center
    rl.insert()  # diff = 4 = max
    assert not rl.await_insert(timeout=0.02)  # another would overshoot
    released = threading.Event()

    def writer() -> None:
        rl.await_insert(timeout=5)
        released.set()

    t = threading.Thread(target=writer)
    t.start()
    wait_blocked([t], rl)
    assert not released.is_set()
    assert rl.take_sample(2, timeout=0)  # diff = 2: room for one more insert
    t.join(2)
    assert released.is_set()


def test_samples_block_when_ahead_and_release_on_insert() -> None:
    rl = Watched(samples_per_insert=1.0, min_size_to_sample=2, error_buffer=1.0)
    rl.insert(2)  # diff 2 = center, min 1
    assert rl.take_sample(timeout=0.01)
    assert not rl.take_sample(timeout=0.02)  # diff 1 - 1 < min
    got = []
    t = threading.Thread(target=lambda: got.append(rl.take_sample(timeout=5)))
    t.start()
    wait_blocked([t], rl)
    assert not got
    rl.insert()
    t.join(2)
    assert got == [True]


def test_ratio_is_kept_by_concurrent_sides() -> None:
    g = 5
    rl = SampleToInsertRatio(samples_per_insert=g, min_size_to_sample=10, error_buffer=g * 2)
    stop = threading.Event()
    worst = [0.0]

    def writer() -> None:
        for _ in range(400):
            rl.await_insert(timeout=5)
            rl.insert()
        stop.set()

    def learner() -> None:
        while not stop.is_set():
            if rl.take_sample(timeout=0.05):
                s = rl.stats()
                worst[0] = max(worst[0], abs(s["diff"] - g * 10))

    ts = [threading.Thread(target=writer), threading.Thread(target=learner)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(20)
    assert stop.is_set()
    s = rl.stats()
    # updates track G per insert within the error buffer (+1 call of overshoot)
    assert worst[0] <= 2 * g + g
    assert abs(s["samples"] - g * (s["inserts"] - 10)) <= 2 * g + g


def test_close_releases_all_waiters() -> None:
    rl = Watched(samples_per_insert=1.0, min_size_to_sample=5, error_buffer=1.0)
    results = []

    def waiter(fn) -> None:
        try:
            fn()
            results.append("returned")
        except RateLimiterClosed:
            results.append("closed")

    rl.insert(6)  # diff 6 > max 6? max = 5 + 1 = 6: one more insert blocks
    threads = [threading.Thread(target=waiter, args=(rl.await_insert,)) for _ in range(3)]
    rl2 = Watched(samples_per_insert=1.0, min_size_to_sample=5, error_buffer=1.0)
    threads += [threading.Thread(target=waiter, args=(rl2.take_sample,)) for _ in range(3)]
    for t in threads:
        t.start()
    wait_blocked(threads, rl, rl2)
    assert results == []
    rl.close()
    rl2.close()
    for t in threads:
        t.join(2)
        assert not t.is_alive()
    assert results == ["closed"] * 6
    with pytest.raises(RateLimiterClosed):
        rl.take_sample(timeout=0)


def test_rejects_window_that_could_deadlock() -> None:
    with pytest.raises(ValueError, match="error_buffer"):
        SampleToInsertRatio(samples_per_insert=5.0, min_size_to_sample=1, error_buffer=2.0)
    with pytest.raises(ValueError, match="error_buffer"):  # G = 3: diff 1 below the centre blocks both
        SampleToInsertRatio(samples_per_insert=3.0, min_size_to_sample=10, error_buffer=1.5)


@pytest.mark.parametrize("extra", [0, 7, -4])  # a warm-up burst's samples beyond the ratio, or fewer
@pytest.mark.parametrize("spi", [0.5, 1.0, 2.0, 3.0, 5.0])
def test_no_window_it_accepts_blocks_both_sides(spi: float, extra: int) -> None:
    rng = np.random.default_rng(0)
    eb = (spi + 1.0) / 2  # the narrowest accepted
    rl = SampleToInsertRatio(samples_per_insert=spi, min_size_to_sample=3, error_buffer=eb,
                             extra_samples=extra)
    for _ in range(3000):
        ops = [op for op, ok in (("insert", rl.can_insert()), ("sample", rl.can_sample())) if ok]
        assert ops, f"both sides blocked at {rl.stats()}"
        if rng.choice(ops) == "insert":
            rl.insert()
        else:
            assert rl.take_sample(timeout=0)


def test_restore_sets_the_counts_of_a_restarted_run() -> None:
    # A replay restarted with 20 stored transitions, warm-up 10, G = 2: 20 inserts and
    # 2 * (20 - 10) samples already happened; the next sample is allowed, the ratio holds.
    rl = SampleToInsertRatio(samples_per_insert=2.0, min_size_to_sample=11, error_buffer=4.0)
    assert not rl.can_sample()
    rl.restore(inserts=20, samples=20)
    assert rl.stats()["inserts"] == 20 and rl.stats()["samples"] == 20
    assert rl.can_sample(2) and not rl.can_sample(3)  # diff 20 - 20 = 22 - 4 + 2: two samples of slack
    with pytest.raises(ValueError, match="counts"):
        rl.restore(-1, 0)


def test_extra_samples_may_be_drawn_at_once_at_min_size_while_inserts_wait() -> None:
    # SAC-AE's warm-up burst: at min size the learner may draw the extra samples with no insert
    # between, inserts wait for them, and from there the ratio holds as without them.
    plain = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=5, error_buffer=2.0)
    burst = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=5, error_buffer=2.0,
                                extra_samples=10)
    for rl in (plain, burst):
        rl.insert(5)
    assert plain.can_insert() and not burst.can_insert()
    drawn = {id(rl): sum(rl.take_sample(timeout=0) for _ in range(30)) for rl in (plain, burst)}
    assert drawn[id(burst)] - drawn[id(plain)] == 10
    for rl in (plain, burst):
        assert rl.await_insert(timeout=0)
        rl.insert()
        assert rl.take_sample(timeout=0) and not rl.can_sample()  # one insert, G = 1 sample
