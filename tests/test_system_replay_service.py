"""The replay service over real Zenoh on loopback: the learner's client, the actor's writer, the run's
config, and bad requests (answered with an error, nothing lost)."""

from __future__ import annotations

import copy
import threading
import time

import numpy as np
import pytest

from nasa.up import free_port
from shared import run_config, wire
from shared.replay.adder import ZenohWriter
from shared.replay.client import ZenohReplayClient
from shared.service import Log, StopFlag
from shared.zenoh_session import open_client, open_router, token_up
from tests.test_replay_service import SPEC, batch, make_service


def wait_for(predicate, what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


class Serving:
    """A router, the replay service on its own session and thread, and a second session."""

    def __init__(self, tmp_path, **kwargs) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.stop = StopFlag()
        self.tmp_path, self.kwargs = tmp_path, kwargs

    def __enter__(self):
        self.router = open_router(self.endpoint)
        self.replay_session = open_client(self.endpoint)
        self.session = open_client(self.endpoint)
        self.svc = make_service(self.tmp_path, session=self.replay_session, stop=self.stop, **self.kwargs)
        self.thread = threading.Thread(target=self.svc.run)
        return self

    def start(self) -> None:
        self.thread.start()
        # Its liveliness token is declared after its queryables: once seen, requests reach it.
        key = self.svc.keys.alive("replay", 0)
        wait_for(lambda: token_up(self.session, key, timeout_s=1.0), "the replay never came up")

    def __exit__(self, *exc) -> None:
        self.stop.set("test done")
        self.thread.join(timeout=15)
        for s in (self.session, self.replay_session, self.router):
            s.close()


def test_the_learners_client_samples_scores_and_joins_the_run(tmp_path):
    with Serving(tmp_path, warmup=4) as srv:
        svc = srv.svc
        assert svc.insert_batch(batch(n=7, last=True)[0]) == 7
        srv.start()
        client = ZenohReplayClient(srv.session, svc.keys, SPEC, Log("test"), timeout_s=10.0)
        rows, seen = client.unscored(after=0, limit=2)
        np.testing.assert_array_equal(rows["index"], [0, 1])
        assert seen == 7 and np.isnan(rows["intrinsic"]).all()
        client.set_intrinsic(rows["index"], np.array([0.25, 0.5], np.float32))
        wait_for(lambda: svc.store._intrinsic[1] == 0.5, "the write-back never landed")
        rows, seen = client.unscored(after=0, limit=8)
        np.testing.assert_array_equal(rows["index"], [2, 3, 4, 5, 6])
        b = client.sample(4, wait_s=2.0)
        assert b is not None and b["obs"].shape == (4, 9, 16, 16) and b["next_obs"].shape == (4, 9, 16, 16)
        assert b["action"].shape == (4, 2) and b["policy_version"].dtype == np.int64
        assert set(b["index"].tolist()) <= set(range(7)) and client.num_inserted == 7
        b["intrinsic"][:] = 1.0  # writable: the scorer fills it in place
        # The run's config, as the replay holds it: a learner with other settings is refused.
        joined = run_config.join(svc.config, srv.session, svc.keys, StopFlag())
        assert joined is not None and joined.spec == SPEC
        other = copy.deepcopy(svc.config)
        other.batch_size += 1
        with pytest.raises(run_config.ConfigMismatch, match="batch_size"):
            run_config.join(other, srv.session, svc.keys, StopFlag())


def test_bad_requests_get_an_error_reply_and_lose_nothing(tmp_path):
    with Serving(tmp_path) as srv:
        svc = srv.svc
        assert svc.insert_batch(batch(n=7, last=True)[0]) == 7
        srv.start()
        k = svc.keys
        requests = {
            "malformed": (k.sample, b"not a sample request"),  # rejected in the Zenoh callback
            "impossible": (k.sample, wire.encode(wire.SampleRequest(0))),  # rejected by its thread
            "wrong type": (k.unscored, wire.encode(wire.SampleRequest(2))),
            "impossible unscored": (k.unscored, wire.encode(wire.UnscoredRequest(0, 0))),
            "unscored": (k.unscored, wire.encode(wire.UnscoredRequest(0, 2))),
        }
        replies = {
            name: list(srv.session.get(key, payload=payload, timeout=10.0))
            for name, (key, payload) in requests.items()
        }
    for name in ("malformed", "impossible", "wrong type", "impossible unscored"):
        [reply] = replies[name]
        assert reply.ok is None and reply.err is not None, name
    assert b"batch_size 0" in replies["impossible"][0].err.payload.to_bytes()
    [reply] = replies["unscored"]  # the service still answers, and its data is intact
    assert wire.decode(reply.ok.payload.to_bytes(), wire.SampleReply).batch_size == 2
    assert svc.invalid == 4 and svc.store.num_inserted == 7


def test_the_actors_writer_inserts_with_backpressure_and_sees_the_replay_go(tmp_path):
    with Serving(tmp_path, warmup=100) as srv:
        svc = srv.svc
        srv.start()
        frames = np.random.default_rng(0).integers(0, 256, (8, *SPEC.frame_shape), dtype=np.uint8)
        writer = ZenohWriter(srv.session, svc.keys, actor_id=3, incarnation=5, frame_shape=SPEC.frame_shape,
                             send_batch=3, max_in_flight=1, stop=StopFlag(), log=Log("test"))
        with writer:
            assert writer.wait_for_replay()
            writer.add_first(frames[0])
            for t in range(1, 8):  # 7 steps: batches of 3, 3 and 1, one in flight at a time
                writer.add(np.full(2, t / 10, np.float32), float(t), 1.0, frames[t], t == 7, policy_version=t)
            wait_for(lambda: writer.global_steps == 7, "the acknowledgements never came")
            assert writer.window.in_flight == 0 and not writer.broken
            b = svc.store.get(np.arange(7))
            np.testing.assert_array_equal(b["next_obs"][:, 6:], frames[1:])
            np.testing.assert_array_equal(b["policy_version"], np.arange(1, 8))
            assert np.isnan(b["intrinsic"]).all()
            srv.stop.set("the replay goes away")
            wait_for(lambda: not writer.window.alive, "the writer never saw the replay go")
            assert writer.broken  # the loop abandons the episode under way


def test_a_replay_started_with_other_settings_than_its_run_folder_exits_2(tmp_path):
    import os
    import subprocess
    import sys

    from shared.config import default_config

    config = default_config("nasa_td3", "cpu-small")
    config.env.task = "cartpole-swingup"
    run_config.open_folder(config, tmp_path)  # the run folder, as `nasa up` writes it
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_router(endpoint):
        env = {**os.environ, "NASA_ZENOH_CONNECT": endpoint, "NASA_RUN_ID": "mismatch"}
        proc = subprocess.run(
            [sys.executable, "-m", "services.replay", "--preset", "cpu-small", "--task", "cartpole-swingup",
             "--batch-size", str(config.batch_size + 1), "--data", str(tmp_path)],
            env=env, capture_output=True, text=True, timeout=120,
        )
    assert proc.returncode == 2, proc.stderr
    assert "batch_size" in proc.stderr
    assert not (tmp_path / "replay").exists()  # refused before opening a store


def test_a_writer_whose_every_batch_the_replay_refuses_stops_its_actor_with_the_reason(tmp_path):
    """Over real Zenoh: the replay has seen a newer incarnation of actor 3, so it refuses every episode
    of incarnation 4 and says so in its acks; the writer counts them and stops its actor, instead
    of acting for ever. The newer incarnation's batches are stored, and acknowledged as such."""
    from shared.replay.adder import REFUSALS_TO_STOP

    with Serving(tmp_path, warmup=100) as srv:
        svc = srv.svc
        svc.insert_batch(batch(actor=3, inc=5, n=2)[0])
        srv.start()
        frames = np.random.default_rng(0).integers(0, 256, (3, *SPEC.frame_shape), dtype=np.uint8)
        stop = StopFlag()
        writer = ZenohWriter(srv.session, svc.keys, actor_id=3, incarnation=4, frame_shape=SPEC.frame_shape,
                             send_batch=1, max_in_flight=1, stop=stop, log=Log("test"))
        with writer:
            assert writer.wait_for_replay()
            episodes = 0
            while not stop:  # each episode: its start is refused for good, its next step as an orphan
                assert episodes < 10 * REFUSALS_TO_STOP, "the writer never gave up"
                writer.add_first(frames[0])
                for t in (1, 2):
                    writer.add(np.zeros(2, np.float32), 0.0, 1.0, frames[t], t == 2, policy_version=0)
                episodes += 1
            assert "older than incarnation 5" in writer.refused_for_good
            assert "older than incarnation 5" in stop.reason
            assert episodes == REFUSALS_TO_STOP and writer.refused == 2 * REFUSALS_TO_STOP - 1
        assert svc.store.num_inserted == 2  # nothing of the older incarnation
        newer = ZenohWriter(srv.session, svc.keys, actor_id=3, incarnation=5, frame_shape=SPEC.frame_shape,
                            send_batch=2, max_in_flight=1, stop=StopFlag(), log=Log("test"))
        with newer:
            assert newer.wait_for_replay()
            newer.add_first(frames[0])
            newer.add(np.zeros(2, np.float32), 0.0, 1.0, frames[1], True, policy_version=0)
            wait_for(lambda: newer.global_steps == 3, "the newer incarnation's ack never came")
            assert newer.refused == 0 and not newer.stop


def test_two_launches_sharing_an_incarnation_are_told_apart_and_the_second_stops(tmp_path):
    """One actor id started on two hosts in the same tenth of a second gets one incarnation on
    both. Their batches carry each launch's random number: the replay keeps the launch it heard
    first, refuses the other's batches for good (that writer stops its actor), and neither takes
    the other's acknowledgements."""
    from shared.replay.adder import REFUSALS_TO_STOP

    frames = np.random.default_rng(0).integers(0, 256, (3, *SPEC.frame_shape), dtype=np.uint8)

    def episode(writer: ZenohWriter) -> None:
        writer.add_first(frames[0])
        for t in (1, 2):
            writer.add(np.zeros(2, np.float32), 0.0, 1.0, frames[t], t == 2, policy_version=0)

    with Serving(tmp_path, warmup=100) as srv, open_client(srv.endpoint) as elsewhere:
        svc = srv.svc
        srv.start()
        first = ZenohWriter(srv.session, svc.keys, actor_id=3, incarnation=5, frame_shape=SPEC.frame_shape,
                            send_batch=1, max_in_flight=1, stop=StopFlag(), log=Log("test"), launch=11)
        second = ZenohWriter(elsewhere, svc.keys, actor_id=3, incarnation=5, frame_shape=SPEC.frame_shape,
                             send_batch=1, max_in_flight=1, stop=StopFlag(), log=Log("test"), launch=22)
        with first, second:
            assert first.wait_for_replay() and second.wait_for_replay()
            episode(first)
            wait_for(lambda: first.global_steps == 2, "the first launch's acks never came")
            episodes = 0
            while not second.stop:
                assert episodes < 10 * REFUSALS_TO_STOP, "the second launch never gave up"
                episode(second)
                episodes += 1
            assert "another launch's" in second.refused_for_good and "--actor-id" in second.refused_for_good
            assert svc.store.num_inserted == 2  # nothing of the second launch
            episode(first)  # the first goes on, untouched by the refusals it heard on its id's key
            wait_for(lambda: first.global_steps == 4, "the first launch's acks never came")
            assert first.refused == 0 and not first.stop and svc.store.num_inserted == 4


def test_a_batch_of_another_frame_shape_is_acknowledged_as_refused_for_good_and_its_writer_stops(tmp_path):
    """Over real Zenoh: frames of a shape not the run's fail the batch's decode. The replay used to
    count it and answer nothing, so its actor waited on the acknowledgement for ever; now it answers
    with the reason, and the writer stops its actor. Nothing is stored."""
    with Serving(tmp_path, warmup=100) as srv:
        svc = srv.svc
        srv.start()
        shape = (3, 8, 8)
        frames = np.random.default_rng(0).integers(0, 256, (2, *shape), dtype=np.uint8)
        stop = StopFlag()
        writer = ZenohWriter(srv.session, svc.keys, actor_id=6, incarnation=2, frame_shape=shape,
                             send_batch=1, max_in_flight=1, stop=stop, log=Log("test"))
        # Only so that a writer never answered fails the test instead of hanging it.
        watchdog = threading.Timer(60.0, stop.set, ["test watchdog"])
        watchdog.start()
        with writer:
            assert writer.wait_for_replay()
            while not stop:
                writer.add_first(frames[0])
                writer.add(np.zeros(2, np.float32), 0.0, 1.0, frames[1], True, policy_version=0)
        watchdog.cancel()
        assert writer.refused_for_good is not None and "shape" in writer.refused_for_good
        assert svc.store.num_inserted == 0 and svc.invalid == writer.refused


def test_a_batch_refused_for_its_launch_number_is_answered_with_an_ack_its_writers_can_read(tmp_path):
    """A batch whose launch number is outside the wire's range does not decode; the replay echoed
    that number in its refusal, an ack no writer can decode, so its sender never heard why. It
    echoes 0 then, which every launch of the incarnation takes."""
    import msgpack

    with Serving(tmp_path, warmup=100) as srv:
        svc = srv.svc
        srv.start()
        acks: list[bytes] = []
        body = msgpack.unpackb(wire.encode(batch(actor=6, inc=2)[0]), raw=False)
        # Declared on the session that sends the batches: the router has it before their refusals.
        with srv.session.declare_subscriber(svc.keys.ack(6), lambda s: acks.append(s.payload.to_bytes())):
            for launch in (-1, 2**63):
                srv.session.put(svc.keys.insert(6), msgpack.packb({**body, "launch": launch}))
            wait_for(lambda: len(acks) == 2, "the refusals never came")
        for ack in [wire.decode(a, wire.InsertAck) for a in acks]:
            assert (ack.actor_id, ack.incarnation, ack.launch) == (6, 2, 0) and "launch" in ack.refused
        assert svc.store.num_inserted == 0
