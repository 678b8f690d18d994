"""The replay service's insert and sample paths, without Zenoh; bad sample requests over a real
Zenoh session on loopback."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from nasa.up import free_port
from services.replay.service import ReplayArgs, ReplayService
from shared import wire
from shared.config import default_config
from shared.service import StopFlag
from shared.zenoh_session import open_client, open_router

SHAPE = (3, 16, 16)


def make_service(tmp_path, warmup=4, steps=100, session=None, stop=None):
    config = default_config("nasa_td3", "cpu-small")
    config.env.image_size, config.warmup_steps, config.steps = 16, warmup, steps
    args = ReplayArgs(config=config, data=tmp_path, error_buffer=4)
    return ReplayService(args, session, StopFlag() if stop is None else stop, action_dim=2)  # type: ignore[arg-type]


def batch(actor=0, inc=1, episode=0, start=0, n=3, last=False, seed=0, shape=SHAPE):
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n, *shape), dtype=np.uint8)
    first = rng.integers(0, 256, (1, *shape), dtype=np.uint8) if start == 0 else None
    lasts = np.zeros(n, np.uint8)
    lasts[-1] = last
    return wire.TransitionBatch(
        actor, inc, episode, start, 0, n, list(shape), wire.encode_frames(frames),
        wire.encode_frames(first) if first is not None else None,
        rng.uniform(-1, 1, (n, 2)).astype("<f4").tobytes(), np.ones(n, "<f4").tobytes(),
        np.ones(n, "<f4").tobytes(), lasts.tobytes(), np.arange(n, dtype="<i8").tobytes(),
    ), frames, first


def test_inserts_are_stitched_by_episode_and_step(tmp_path):
    svc = make_service(tmp_path)
    msg, frames, first = batch(n=3)
    assert svc.insert_batch(msg) == 3
    assert svc.insert_batch(batch(start=3, n=2, seed=1)[0]) == 2
    # a gap, another episode, or a restarted actor's old episode are never stitched
    assert svc.insert_batch(batch(start=9, n=2)[0]) == 0
    assert svc.insert_batch(batch(episode=5, start=5, n=2)[0]) == 0
    assert svc.insert_batch(batch(inc=2, start=5, n=2)[0]) == 0
    assert svc.dropped == 6 and svc.store.num_inserted == 5
    # a new incarnation starting an episode is accepted; the replay rejects an older one
    assert svc.insert_batch(batch(inc=2, n=2, last=True)[0]) == 2
    with pytest.raises(ValueError, match="older"):
        svc.insert_batch(batch(inc=1, n=1)[0])
    with pytest.raises(wire.WireError, match="frame shape"):
        svc.insert_batch(batch(inc=3, shape=(3, 8, 8))[0])
    svc.store.close()


def test_warmup_transitions_carry_zero_intrinsic_and_samples_follow_the_ratio(tmp_path):
    svc = make_service(tmp_path, warmup=4)
    rng = np.random.default_rng(0)
    req = wire.SampleRequest(8, wait_s=0.0)
    msg, frames, first = batch(n=5)
    msg4 = wire.TransitionBatch(**{**msg.__dict__, "n": 4, "frames": wire.encode_frames(frames[:4]),
                                   "actions": msg.actions[:32], "rewards": msg.rewards[:16],
                                   "discounts": msg.discounts[:16], "lasts": msg.lasts[:4],
                                   "policy_versions": msg.policy_versions[:32]})
    assert svc.insert_batch(msg4) == 4
    assert not svc.sample(req, rng).ok  # the first sample needs warm-up + 1 inserts
    rest = wire.TransitionBatch(**{**msg.__dict__, "start": 4, "n": 1, "first_frame": None,
                                   "frames": wire.encode_frames(frames[4:]), "actions": msg.actions[32:],
                                   "rewards": msg.rewards[16:], "discounts": msg.discounts[16:],
                                   "lasts": msg.lasts[4:], "policy_versions": msg.policy_versions[32:]})
    assert svc.insert_batch(rest) == 1
    intr = svc.store._intrinsic[:5]
    assert np.all(intr[:4] == 0) and math.isnan(intr[4])
    oks = [svc.sample(req, rng).ok for _ in range(10)]
    assert sum(oks) == 4  # the error buffer of 4 samples, then inserts must come
    assert svc.insert_batch(batch(start=5, n=2, seed=2)[0]) == 2
    reply = svc.sample(req, rng)
    assert reply.ok and reply.window_shape == [8, 12, 16, 16]
    window = wire.array(reply.window, "u1", tuple(reply.window_shape))
    index = wire.array(reply.index, "<i8", (8,))
    for row, g in zip(window, index, strict=True):
        # newest frame of the window is the transition's next frame
        if g < 5:
            np.testing.assert_array_equal(row[9:], frames[g])
    svc.store.close()


def test_unscored_requests_return_the_oldest_unscored_rows_outside_the_ratio(tmp_path):
    svc = make_service(tmp_path, warmup=4)
    rng = np.random.default_rng(0)
    msg, frames, first = batch(n=7, last=True)
    assert svc.insert_batch(msg) == 7  # rows 0-3 warm-up (scored 0), rows 4-6 unscored
    samples = svc.limiter.samples
    reply = svc.sample(wire.SampleRequest(2, unscored_after=0), rng)
    assert reply.ok and reply.batch_size == 2 and reply.num_inserted == 7
    np.testing.assert_array_equal(wire.array(reply.index, "<i8", (2,)), [4, 5])
    window = wire.array(reply.window, "u1", tuple(reply.window_shape))
    np.testing.assert_array_equal(window[0, 9:], frames[4])  # row 4's newest frame
    assert np.isnan(wire.array(reply.intrinsic, "<f4", (2,))).all()
    svc.store.set_intrinsic(np.array([4, 5]), np.array([0.5, 0.5]))
    reply = svc.sample(wire.SampleRequest(8, unscored_after=0), rng)
    np.testing.assert_array_equal(wire.array(reply.index, "<i8", (reply.batch_size,)), [6])
    svc.store.set_intrinsic(np.array([6]), np.array([0.5]))
    reply = svc.sample(wire.SampleRequest(8, unscored_after=5), rng)
    assert not reply.ok and reply.reason == "none unscored" and reply.num_inserted == 7
    assert svc.limiter.samples == samples  # scoring requests are not training samples
    svc.store.close()


def test_bad_sample_requests_get_an_error_reply_and_lose_nothing(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop = StopFlag()
    with open_router(endpoint), open_client(endpoint) as replay_session, open_client(endpoint) as learner:
        svc = make_service(tmp_path, session=replay_session, stop=stop)
        assert svc.insert_batch(batch(n=7, last=True)[0]) == 7
        serving = threading.Thread(target=svc.run)
        serving.start()
        try:
            # Its liveliness token is declared after its queryable: once seen, requests reach it.
            deadline = time.monotonic() + 10
            while not list(learner.liveliness().get(svc.keys.alive("replay", 0), timeout=1.0)):
                assert time.monotonic() < deadline, "the replay never came up"
                time.sleep(0.1)
            requests = {
                "malformed": b"not a sample request",  # rejected in the Zenoh callback
                "impossible": wire.encode(wire.SampleRequest(0)),  # rejected by the sampling thread
                "scoring": wire.encode(wire.SampleRequest(2, unscored_after=0)),
            }
            replies = {
                name: list(learner.get(svc.keys.sample, payload=payload, timeout=10.0))
                for name, payload in requests.items()
            }
        finally:
            stop.set("test done")
            serving.join(timeout=15)
    for name in ("malformed", "impossible"):
        [reply] = replies[name]
        assert reply.ok is None and reply.err is not None, name
    assert b"batch_size 0" in replies["impossible"][0].err.payload.to_bytes()
    [reply] = replies["scoring"]  # the service still answers, and its data is intact
    assert wire.decode(reply.ok.payload.to_bytes(), wire.SampleReply).batch_size == 2
    assert svc.invalid == 2 and svc.store.num_inserted == 7
