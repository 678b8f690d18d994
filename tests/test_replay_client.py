"""The replay client without Zenoh: LocalReplay over a store, the wire encoding of a batch, the
Zenoh client's handling of bad or missing replies (fake session), and the Prefetcher."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from shared import wire
from shared.envs import EnvSpec
from shared.replay import ReplayStore, SampleToInsertRatio
from shared.replay.client import (
    BATCH_KEYS,
    LocalReplay,
    Prefetcher,
    ZenohReplayClient,
    decode_reply,
    encode_reply,
)
from shared.service import Log, StopFlag

SPEC = EnvSpec((3, 8, 8), 3, 2)


def filled(n: int, capacity: int = 100) -> ReplayStore:
    store = ReplayStore(capacity, SPEC.frame_shape, SPEC.frame_stack, SPEC.action_dim)
    rng = np.random.default_rng(0)
    ep = store.begin_episode(rng.integers(0, 256, SPEC.frame_shape, dtype=np.uint8))
    for t in range(n):
        frame = rng.integers(0, 256, SPEC.frame_shape, dtype=np.uint8)
        store.add(ep, rng.uniform(-1, 1, 2), float(t), 1.0, frame, t == n - 1, policy_version=t)
    return store


def test_local_replay_samples_the_client_batch():
    local = LocalReplay(filled(20), np.random.default_rng(0))
    b = local.sample(8)
    assert set(b) == set(BATCH_KEYS) and local.num_inserted == 20
    assert b["obs"].shape == (8, 9, 8, 8) and b["next_obs"].shape == (8, 9, 8, 8)
    np.testing.assert_array_equal(b["obs"][:, 3:], b["next_obs"][:, :6])  # one window, two views
    np.testing.assert_array_equal(b["policy_version"], b["index"])
    b["intrinsic"][:] = 0.5  # writable
    assert LocalReplay(filled(0), np.random.default_rng(0)).sample(8) is None  # empty: not ready


def test_local_replay_is_paced_by_its_limiter():
    store = filled(6)
    limiter = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=5, error_buffer=1.0)
    limiter.restore(inserts=6, samples=0)
    local = LocalReplay(store, np.random.default_rng(0), limiter)
    got = [local.sample(4) is not None for _ in range(4)]
    assert got == [True, True, False, False]  # diff 6 - samples must stay >= 5 - 1
    assert local.draw(4)[1] == "rate limited"


def test_local_replay_without_replacement():
    local = LocalReplay(filled(10), np.random.default_rng(0), replace=False)
    assert local.sample(11) is None  # never a smaller batch
    assert "fewer than 11" in local.draw(11)[1]
    for _ in range(10):
        assert len(set(local.sample(10)["index"].tolist())) == 10


def test_unscored_returns_the_oldest_unscored_rows_and_the_count_before_the_scan():
    local = LocalReplay(filled(10), np.random.default_rng(0))
    local.set_intrinsic(np.array([0, 2]), np.array([0.0, 1.0]))
    rows, seen = local.unscored(after=0, limit=3)
    np.testing.assert_array_equal(rows["index"], [1, 3, 4])
    assert seen == 10 and np.isnan(rows["intrinsic"]).all()
    local.set_intrinsic(np.arange(10), np.zeros(10))
    assert local.unscored(after=4, limit=3) == (None, 10)


def test_a_batch_survives_the_wire_and_is_checked_against_the_spec():
    store = filled(20)
    sampled = store.sample(5, np.random.default_rng(1))
    reply = wire.decode(wire.encode(encode_reply(sampled, 20)), wire.SampleReply)
    b = decode_reply(reply, SPEC)
    for key in BATCH_KEYS:
        np.testing.assert_array_equal(b[key], sampled[key], err_msg=key)
        assert b[key].flags.writeable, key
    with pytest.raises(wire.WireError, match="window shape"):
        decode_reply(reply, EnvSpec((3, 8, 8), 2, 2))  # another frame stack
    with pytest.raises(wire.WireError, match="expected"):
        decode_reply(reply, EnvSpec((3, 8, 8), 3, 4))  # another action size


class FakeSession:
    """Answers every get with the given replies (or raises), records puts."""

    def __init__(self, replies) -> None:
        self.replies, self.puts, self.gets = replies, [], []

    def get(self, key, payload, timeout, congestion_control):
        self.gets.append((key, payload))
        if isinstance(self.replies, Exception):
            raise self.replies
        return self.replies

    def put(self, key, payload, congestion_control):
        self.puts.append((key, payload))


def ok_reply(msg: wire.Message) -> SimpleNamespace:
    data = wire.encode(msg)
    return SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data)), err=None)


def err_reply(text: bytes) -> SimpleNamespace:
    return SimpleNamespace(ok=None, err=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: text)))


def client(replies) -> ZenohReplayClient:
    return ZenohReplayClient(FakeSession(replies), wire.Keys("t"), SPEC, Log("test"), timeout_s=1.0)


def test_zenoh_client_decodes_good_replies_and_counts_bad_ones():
    sampled = filled(20).sample(4, np.random.default_rng(0))
    c = client([ok_reply(encode_reply(sampled, 20))])
    b = c.sample(4, wait_s=0.0)
    np.testing.assert_array_equal(b["index"], sampled["index"])
    assert c.num_inserted == 20 and c.invalid == 0
    key, payload = c.session.gets[0]
    assert key == c.keys.sample and wire.decode(payload, wire.SampleRequest).batch_size == 4
    rows, seen = c.unscored(after=3, limit=4)
    assert c.session.gets[1][0] == c.keys.unscored and seen == 20
    assert wire.decode(c.session.gets[1][1], wire.UnscoredRequest) == wire.UnscoredRequest(3, 4)
    # not ready: None, and the count it brings is kept
    c = client([ok_reply(wire.SampleReply(False, "rate limited", 30))])
    assert c.sample(4, wait_s=0.0) is None and c.num_inserted == 30 and c.invalid == 0
    assert c.unscored(after=5, limit=4) == (None, 30)
    for bad in ([err_reply(b"batch_size 0")], [ok_reply(wire.Stop("x"))]):
        c = client(bad)
        assert c.sample(4, wait_s=0.0) is None and c.invalid == 1
    wrong = wire.SampleReply(**{**encode_reply(sampled, 20).__dict__, "window_shape": [4, 12, 8, 9]})
    c = client([ok_reply(wrong)])
    assert c.sample(4, wait_s=0.0) is None and c.invalid == 1


def test_zenoh_client_refuses_a_count_past_the_step_budget_and_keeps_its_own():
    """The client keeps the largest count it has seen: one bad count would stay."""
    bad = ok_reply(wire.SampleReply(False, "rate limited", 2**61))
    c = ZenohReplayClient(FakeSession([bad]), wire.Keys("t"), SPEC, Log("test"), timeout_s=1.0, steps=200)
    assert c.sample(4, wait_s=0.0) is None and c.invalid == 1 and c.num_inserted == 0
    c.session.replies = [ok_reply(wire.SampleReply(False, "rate limited", 30))]
    assert c.sample(4, wait_s=0.0) is None and c.invalid == 1 and c.num_inserted == 30


def test_zenoh_client_without_a_replay_claims_nothing_scored():
    c = client([])  # nobody answered
    assert c.sample(4, wait_s=0.0) is None
    assert c.unscored(after=7, limit=4) == (None, 7)


def test_set_intrinsic_puts_the_scores():
    c = client([])
    c.set_intrinsic(np.array([3, 4]), np.array([0.5, 0.25]))
    [(key, payload)] = c.session.puts
    msg = wire.decode(payload, wire.SetIntrinsic)
    assert key == c.keys.intrinsic
    np.testing.assert_array_equal(np.frombuffer(msg.index, "<i8"), [3, 4])
    np.testing.assert_array_equal(np.frombuffer(msg.value, "<f4"), [0.5, 0.25])


def test_set_intrinsic_sends_more_scores_than_the_replay_takes_at_once_in_parts_it_accepts():
    """The warm-up's zeros go out as one call of warmup_steps rows, which can exceed MAX_BATCH."""
    c = client([])
    n = 2 * wire.MAX_BATCH + 5
    c.set_intrinsic(np.arange(n), np.zeros(n))
    parts = [wire.decode(payload, wire.SetIntrinsic, c.bounds) for _, payload in c.session.puts]
    assert [len(p.index) // 8 for p in parts] == [wire.MAX_BATCH, wire.MAX_BATCH, 5]
    sent = np.concatenate([np.frombuffer(p.index, "<i8") for p in parts])
    np.testing.assert_array_equal(sent, np.arange(n))


def test_prefetcher_keeps_batches_ready_and_counts_misses():
    class Flaky:
        """Not ready on every other request."""

        def __init__(self) -> None:
            self.local, self.calls = LocalReplay(filled(20), np.random.default_rng(0)), 0

        def sample(self, batch_size, wait_s):
            self.calls += 1
            return self.local.sample(batch_size) if self.calls % 2 == 0 else None

    source = Flaky()
    with Prefetcher(source, batch_size=6, threads=2, stop=StopFlag()) as prefetch:
        batches = [prefetch.get(timeout=10.0) for _ in range(5)]
    assert all(b is not None and b["obs"].shape[0] == 6 for b in batches)
    assert prefetch.misses >= 1 and prefetch.last_miss is not None
    assert all(not t.is_alive() for t in prefetch._threads)  # closed on exit


class Gated:
    """A replay whose every request waits for the test to release it; counts what it served."""

    def __init__(self) -> None:
        self.local = LocalReplay(filled(20), np.random.default_rng(0))
        self.asked, self.served = threading.Semaphore(0), 0
        self.release = threading.Semaphore(0)

    def sample(self, batch_size, wait_s):
        self.asked.release()
        self.release.acquire()
        self.served += 1
        return self.local.sample(batch_size)


def test_prefetcher_counts_every_batch_served_even_one_held_by_a_thread_with_the_queue_full():
    source = Gated()
    with Prefetcher(source, batch_size=4, threads=2, stop=StopFlag()) as prefetch:
        for _ in range(3):  # two fill the queue, the third waits in its thread's hands
            assert source.asked.acquire(timeout=10.0)
            source.release.release()
        assert source.asked.acquire(timeout=10.0)  # the fourth request is in flight
        with prefetch.paused(timeout=0.5) as quiet:
            assert not quiet  # the fourth is still unanswered
        source.release.release()
        with prefetch.paused(timeout=10.0) as quiet:
            assert quiet
            assert prefetch.drawn == source.served == 4  # not the queue's two
            assert not source.asked.acquire(timeout=0.5)  # no request is sent while paused
        taken = [prefetch.get(timeout=10.0) for _ in range(4)]
        assert all(b is not None for b in taken)
        for _ in range(10):  # let the threads finish and stop
            source.release.release()


def test_the_replays_sampler_threads_never_draw_more_batches_than_the_limiter_allows():
    class Preempted(SampleToInsertRatio):
        """Every call returns late, as if its thread lost the CPU right after it."""

        def take_sample(self, *args, **kwargs):
            taken = super().take_sample(*args, **kwargs)
            time.sleep(0.002)
            return taken

    store = filled(20)
    limiter = Preempted(samples_per_insert=1.0, min_size_to_sample=1, error_buffer=1.0)
    limiter.insert(30)  # exactly 30 batches allowed
    start, drawn = threading.Barrier(4), []

    def sampler(seed: int) -> None:
        local = LocalReplay(store, np.random.default_rng(seed), limiter)
        start.wait()
        while (batch := local.draw(4, wait_s=0.05)[0]) is not None:
            drawn.append(batch)

    threads = [threading.Thread(target=sampler, args=(seed,)) for seed in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert len(drawn) == limiter.stats()["samples"] == 30
