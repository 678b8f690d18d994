"""The actor's side of the replay without Zenoh: backpressure, acknowledgements, replay loss, ack
timeout (SendWindow), batching and episode abandonment (ZenohWriter on a fake publisher), and the
in-process StoreAdder."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest

from shared import wire
from shared.replay.adder import REFUSALS_TO_STOP, SendWindow, StoreAdder, ZenohWriter
from shared.replay.store import ReplayStore
from shared.service import Log, StopFlag

SHAPE = (3, 8, 8)


class FakeClock:
    """Each reading advances the clock by `step` seconds: a wait of a minute takes microseconds."""

    def __init__(self, step: float) -> None:
        self.now, self.step = 0.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def window(max_in_flight=2, clock=None, messages=None) -> SendWindow:
    log = (messages.append if messages is not None else lambda _: None)
    return SendWindow(max_in_flight, log, poll_s=0.001, clock=clock or FakeClock(0.0))


def test_at_most_max_in_flight_batches_then_the_writer_waits_for_an_ack():
    w, stop = window(max_in_flight=2), StopFlag()
    w.on_replay(True)
    assert w.acquire(stop) and w.acquire(stop) and w.in_flight == 2
    acquired = threading.Event()
    t = threading.Thread(target=lambda: w.acquire(stop) and acquired.set())
    t.start()
    assert not acquired.wait(0.05)  # backpressure: a third batch waits
    w.on_ack(num_inserted=16)
    t.join(5)
    assert acquired.is_set() and w.in_flight == 2 and w.global_steps == 16
    w.on_ack(num_inserted=8)  # an older count never moves global_steps back
    assert w.global_steps == 16 and w.in_flight == 1


def test_stop_releases_a_waiting_writer_without_counting_the_batch():
    w, stop = window(max_in_flight=1), StopFlag()
    assert w.acquire(stop)
    result = []
    t = threading.Thread(target=lambda: result.append(w.acquire(stop)))
    t.start()
    stop.set("test")
    w.wake()
    t.join(5)
    assert result == [False] and w.in_flight == 1


def test_replay_gone_loses_the_in_flight_batches_and_breaks_the_episode():
    messages: list[str] = []
    w, stop = window(max_in_flight=3, messages=messages), StopFlag()
    w.on_replay(True)
    w.acquire(stop)
    w.acquire(stop)
    w.on_replay(False)
    assert w.in_flight == 0 and w.lost == 2 and w.broken and not w.alive
    assert any("gone" in m for m in messages)
    assert not any("back" in m for m in messages)
    assert not w.acquire(stop)  # no batch of the broken episode is sent
    w.on_replay(True)
    assert messages[-1].startswith("the replay is back")  # only after it had gone
    assert w.broken  # still: the episode under way stays abandoned
    w.begin_episode()  # a new episode starts from its reset frame: accepted whatever came before
    assert not w.broken and w.acquire(stop) and w.in_flight == 1
    w.on_replay(False)
    w.begin_episode()  # the replay went during the reset: this episode is not sent either
    assert w.broken and not w.acquire(stop)


def test_a_writer_blocked_when_the_replay_goes_is_released_and_sends_nothing():
    w, stop = window(max_in_flight=1), StopFlag()
    w.on_replay(True)
    w.acquire(stop)
    result = []
    t = threading.Thread(target=lambda: result.append(w.acquire(stop)))
    t.start()
    w.on_replay(False)
    t.join(5)
    assert result == [False] and w.in_flight == 0


def one_in_flight(messages: list[str]) -> tuple[SendWindow, StopFlag]:
    """A window of one batch, that batch sent, on a clock where a minute passes in microseconds."""
    w, stop = window(max_in_flight=1, clock=FakeClock(step=7.0), messages=messages), StopFlag()
    w.on_replay(True)
    assert w.acquire(stop)
    return w, stop


def test_no_ack_for_the_timeout_counts_the_in_flight_batches_lost():
    messages: list[str] = []
    w, stop = one_in_flight(messages)
    # The replay goes on storing (other actors' batches), but never acknowledges this one.
    threading.Timer(0.05, lambda: w.observe(8)).start()
    assert w.acquire(stop)  # returns once a (fake) minute has passed without an ack
    assert w.lost == 1 and w.in_flight == 1
    assert any("assuming the 1 in-flight batches lost" in m for m in messages)


def test_a_replay_that_stores_nothing_is_waited_on_not_sent_more():
    # Its rate limiter holds inserts while the learner is away: more batches would only queue there.
    messages: list[str] = []
    w, stop = one_in_flight(messages)
    result: list[bool] = []
    t = threading.Thread(target=lambda: result.append(w.acquire(stop)))
    t.start()
    deadline = time.monotonic() + 30
    while sum("stored nothing since" in m for m in messages) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert t.is_alive() and w.lost == 0 and w.in_flight == 1
    w.on_ack(9)  # the learner is back: the replay takes it
    t.join(5)
    assert result == [True] and w.lost == 0


def test_wait_alive_returns_when_the_replay_appears_or_on_stop():
    w, stop = window(), StopFlag()
    t = threading.Thread(target=lambda: w.on_replay(True))
    t.start()
    assert w.wait_alive(stop)
    t.join()
    w.on_replay(False)
    stop.set("test")
    assert not w.wait_alive(stop)


def test_observe_tracks_the_newest_count_and_done():
    w = window()
    w.observe(100, done=False)
    w.observe(50)
    assert w.global_steps == 100 and not w.replay_done
    w.observe(200, done=True)
    assert w.global_steps == 200 and w.replay_done


# -- ZenohWriter's batching, on a fake publisher ----------------------------------------------


class FakePublisher:
    def __init__(self) -> None:
        self.sent: list[wire.TransitionBatch] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(wire.decode(payload, wire.TransitionBatch))


def make_writer(send_batch=3, max_in_flight=8, budget=None) -> tuple[ZenohWriter, FakePublisher]:
    writer = ZenohWriter(None, wire.Keys("t"), actor_id=4, incarnation=9, frame_shape=SHAPE,
                         send_batch=send_batch, max_in_flight=max_in_flight, stop=StopFlag(), log=Log("test"),
                         budget=budget)
    writer._publisher = publisher = FakePublisher()
    writer.window.on_replay(True)
    return writer, publisher


def frames(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, *SHAPE), dtype=np.uint8)


def ack(actor_id: int, incarnation: int, n: int) -> SimpleNamespace:
    data = wire.encode(wire.InsertAck(actor_id, incarnation, n))
    return SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data))


def test_steps_go_in_batches_with_the_first_frame_once_and_the_last_batch_short():
    writer, pub = make_writer(send_batch=3)
    f = frames(8)
    writer.add_first(f[0])
    for t in range(1, 8):
        writer.add(np.full(2, 0.1, np.float32), float(t), 1.0, f[t], t == 7, policy_version=t)
    assert [(m.episode, m.start, m.n) for m in pub.sent] == [(0, 0, 3), (0, 3, 3), (0, 6, 1)]
    assert pub.sent[0].first_frame is not None and pub.sent[1].first_frame is None
    np.testing.assert_array_equal(wire.decode_frames(pub.sent[0].first_frame, 1, SHAPE)[0], f[0])
    sent = np.concatenate([wire.decode_frames(m.frames, m.n, SHAPE) for m in pub.sent])
    np.testing.assert_array_equal(sent, f[1:])
    versions = np.concatenate([wire.array(m.policy_versions, "<i8", (m.n,)) for m in pub.sent])
    np.testing.assert_array_equal(versions, np.arange(1, 8))
    assert all(m.actor_id == 4 and m.incarnation == 9 for m in pub.sent)
    writer.add_first(f[0])  # the next episode numbers on
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[1], True, 7)
    assert (pub.sent[-1].episode, pub.sent[-1].start) == (1, 0)


def test_a_count_past_the_step_budget_is_refused_and_does_not_end_the_acting():
    writer, _ = make_writer(budget=200)
    writer._on_ack(ack(4, 9, 2**61))
    stats = wire.encode(wire.ReplayStats(60, 1, 2**61, 60, 0, 0, 0, False))
    writer._on_stats(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: stats)))
    assert writer.invalid == 2 and writer.global_steps == 0 and not writer.replay_done
    writer._on_ack(ack(4, 9, 200))
    assert writer.invalid == 2 and writer.replay_done


def refusal(reason: str, lasting: bool) -> SimpleNamespace:
    data = wire.encode(wire.InsertAck(4, 9, 0, reason, lasting))
    return SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data))


def test_refused_batches_are_counted_logged_once_and_lasting_ones_stop_the_actor():
    writer, _ = make_writer()
    logged: list[str] = []
    writer.log = logged.append
    for _ in range(REFUSALS_TO_STOP - 1):  # an episode start refused for good, then its orphans
        writer._on_ack(refusal("stale", True))
        writer._on_ack(refusal("orphan", False))
        writer._on_ack(refusal("orphan", False))
    assert writer.refused == 3 * (REFUSALS_TO_STOP - 1) and not writer.stop
    assert len(logged) == 2 and "for good" in logged[0] and "this once" in logged[1]
    writer._on_ack(ack(4, 9, 5))  # a batch stored: the run of lasting refusals starts again
    for _ in range(REFUSALS_TO_STOP - 1):
        writer._on_ack(refusal("stale", True))
    assert not writer.stop and writer.refused_for_good is None
    writer._on_ack(refusal("stale", True))
    assert writer.stop and writer.refused_for_good == "stale" and "stale" in writer.stop.reason
    assert len(logged) == 2


def test_an_ack_of_an_older_replay_without_the_refusal_fields_reads_as_stored():
    old = wire.encode(wire.InsertAck(4, 9, 7))
    body = msgpack.unpackb(old)
    del body["refused"], body["lasting"]
    ack = wire.decode(msgpack.packb(body), wire.InsertAck)
    assert ack.refused == "" and not ack.lasting and ack.num_inserted == 7


def test_acks_of_another_incarnation_are_ignored():
    writer, _ = make_writer(max_in_flight=2)
    writer.window.acquire(writer.stop)
    writer._on_ack(ack(4, 8, 100))  # a previous incarnation's ack
    assert writer.window.in_flight == 1 and writer.global_steps == 0
    writer._on_ack(ack(4, 9, 100))
    assert writer.window.in_flight == 0 and writer.global_steps == 100


def test_acks_of_another_launch_of_the_same_incarnation_are_ignored_an_older_replays_are_not():
    writer, pub = make_writer(max_in_flight=2)
    writer.launch = 7
    writer.window.acquire(writer.stop)
    data = wire.encode(wire.InsertAck(4, 9, 100, launch=8))  # the twin launch's ack
    writer._on_ack(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data)))
    assert writer.window.in_flight == 1 and writer.global_steps == 0
    writer._on_ack(ack(4, 9, 100))  # an older replay's: no launch, 0
    assert writer.window.in_flight == 0 and writer.global_steps == 100
    f = frames(2)
    writer.add_first(f[0])
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[1], True, 0)
    assert pub.sent[-1].launch == 7
    # A batch of an older actor, without the field, reads as launch 0.
    body = msgpack.unpackb(wire.encode(pub.sent[-1]))
    del body["launch"]
    assert wire.decode(msgpack.packb(body), wire.TransitionBatch).launch == 0


def test_a_broken_episode_sends_nothing_more_and_the_next_one_starts_clean():
    writer, pub = make_writer(send_batch=2)
    f = frames(6)
    writer.add_first(f[0])
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[1], False, 0)
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[2], False, 0)
    assert len(pub.sent) == 1
    writer.window.on_replay(False)  # the replay goes
    writer.window.on_replay(True)  # and comes back
    assert writer.broken
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[3], False, 0)
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[4], True, 0)
    assert len(pub.sent) == 1  # the rest of the broken episode is never sent
    writer.add_first(f[0])
    writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[5], True, 0)
    assert (pub.sent[-1].episode, pub.sent[-1].start, pub.sent[-1].first_frame is not None) == (1, 0, True)


def test_the_count_an_actor_warms_up_on_holds_its_steps_not_acknowledged_yet():
    writer, _ = make_writer(send_batch=3)
    f = frames(8)
    writer.add_first(f[0])
    for t in range(1, 8):  # two batches sent, the seventh step waits for its batch
        writer.add(np.zeros(2, np.float32), 0.0, 1.0, f[t], False, 0)
    assert (writer.global_steps, writer.steps_at_least) == (0, 7)
    writer._on_ack(ack(4, 9, 3))
    assert (writer.global_steps, writer.steps_at_least) == (3, 7)
    writer._on_ack(ack(4, 9, 6))
    assert writer.steps_at_least == 7
    writer.observe(50)  # other actors' inserts, seen in the replay's stats
    assert writer.steps_at_least == 51  # which cannot hold the step not sent yet
    lost, _ = make_writer(send_batch=3)
    lost.add_first(f[0])
    for t in range(1, 4):
        lost.add(np.zeros(2, np.float32), 0.0, 1.0, f[t], False, 0)
    lost.window.on_replay(False)  # gone: the batch in flight never lands
    assert (lost.steps_at_least, lost.window.lost) == (0, 1)


def test_writer_rejects_frames_of_another_shape_and_steps_before_an_episode():
    writer, _ = make_writer()
    with pytest.raises(RuntimeError, match="add_first"):
        writer.add(np.zeros(2, np.float32), 0.0, 1.0, frames(1)[0], False, 0)
    with pytest.raises(ValueError, match="expected uint8"):
        writer.add_first(np.zeros((3, 4, 4), np.uint8))


# -- StoreAdder ---------------------------------------------------------------------------------


def test_store_adder_writes_unscored_rows_in_order():
    store = ReplayStore(100, SHAPE, 2, 2)
    adder = StoreAdder(store)
    f = frames(5)
    with pytest.raises(RuntimeError, match="add_first"):
        adder.add(np.zeros(2), 0.0, 1.0, f[1], False, 0)
    adder.add_first(f[0])
    for t in range(1, 5):
        adder.add(np.full(2, 0.5), float(t), 0.99, f[t], t == 4, policy_version=3)
        assert adder.last_index == t - 1
    b = store.get(np.arange(4))
    np.testing.assert_array_equal(b["next_obs"][:, 3:], f[1:])
    np.testing.assert_array_equal(b["obs"][0], np.concatenate([f[0], f[0]]))  # reset frame repeated
    assert np.isnan(b["intrinsic"]).all() and (b["policy_version"] == 3).all()
    assert np.allclose(b["discount"], 0.99) and store.stats()["open_episodes"] == 0
    with pytest.raises(RuntimeError, match="add_first"):  # the episode ended with its last step
        adder.add(np.zeros(2), 0.0, 1.0, f[1], False, 0)


def test_an_ack_that_reaches_the_step_budget_ends_the_acting_before_the_replays_stats_say_so():
    writer, _ = make_writer(max_in_flight=2)
    writer.budget = 100
    writer.window.acquire(writer.stop)
    writer._on_ack(ack(4, 9, 99))
    assert not writer.replay_done
    writer.window.acquire(writer.stop)
    writer._on_ack(ack(4, 9, 100))
    assert writer.replay_done and not writer.window.replay_done  # no stats yet
