"""The wire schema: round trips, validation that rejects bad messages, frame and tensor payloads."""

from __future__ import annotations

import math
import struct

import msgpack
import numpy as np
import pytest
import torch

from shared import wire
from tests.test_robot_bridge_wire import BRIDGE_MESSAGES


def f4(*values: float) -> bytes:
    return np.asarray(values, "<f4").tobytes()


def test_every_message_round_trips():
    frame = wire.encode_frames(np.zeros((1, 3, 8, 8), np.uint8))
    msgs = [
        wire.TransitionBatch(1, 2, 3, 0, 1, [3, 8, 8], frame, frame, f4(0.5), f4(1.0), f4(1.0),
                             b"\x01", np.int64(7).tobytes()),
        wire.InsertAck(1, 2, 100),
        wire.SampleRequest(64, 1.5),
        wire.UnscoredRequest(100, 64),
        wire.SampleReply(False, "rate limited", 10),
        wire.SetIntrinsic(np.int64(3).tobytes(), f4(0.25)),
        wire.ReplayStats(1, 2, 3, 4, 5, 6, 7, False),
        wire.Weights(1, 5, 100, {"w": ["<f4", [1], b"\0\0\0\0"]}),
        wire.ActorStatus(0, 1, 10, 1, 5, 3.5, [[1.0, 125]]),
        wire.EvalResult(1000, 7, [1.0, 2.0]),
        wire.RunConfigMsg({"config": {"seed": 0}}, "0123456789abcdef"),
        wire.Stop("done"),
        *BRIDGE_MESSAGES,
    ]
    assert {type(m) for m in msgs} == set(wire.MESSAGES.values())
    for m in msgs:
        assert wire.decode(wire.encode(m), type(m)) == m


def test_sample_request_default_is_filled():
    body = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "sample_request", "batch_size": 8})
    assert wire.decode(body, wire.SampleRequest).wait_s == 2.0


@pytest.mark.parametrize(
    "body, match",
    [
        (b"\xc1garbage", "not msgpack"),
        (msgpack.packb([1, 2]), "not a map"),
        (msgpack.packb({"v": 999, "t": "stop", "reason": "x"}), "schema version"),
        (msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "insert_ack", "reason": "x"}), "message type"),
        (msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "stop"}), "missing field"),
        (msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "stop", "reason": 5}), "reason"),
    ],
)
def test_bad_messages_raise_wire_error(body, match):
    with pytest.raises(wire.WireError, match=match):
        wire.decode(body, wire.Stop)


def test_field_types_are_checked():
    good = wire.encode(wire.InsertAck(1, 2, 5))
    body = msgpack.unpackb(good)
    bad_fields = (("incarnation", "3"), ("num_inserted", 1.5), ("num_inserted", True), ("actor_id", None))
    for field, bad in bad_fields:
        with pytest.raises(wire.WireError, match=field):
            wire.decode(msgpack.packb({**body, field: bad}), wire.InsertAck)
    # int where float is declared is fine; None only where declared optional
    status = msgpack.unpackb(wire.encode(wire.ActorStatus(0, 1, 2, 3, 4, 5.0, [])))
    assert wire.decode(msgpack.packb({**status, "steps_per_s": 5}), wire.ActorStatus).steps_per_s == 5
    frame = wire.encode_frames(np.zeros((1, 3, 8, 8), np.uint8))
    batch = wire.TransitionBatch(1, 2, 3, 8, 1, [3, 8, 8], frame, None, f4(0.0), f4(0.0), f4(1.0), b"\0",
                                 np.int64(0).tobytes())
    assert wire.decode(wire.encode(batch), wire.TransitionBatch).first_frame is None


def test_frames_whose_header_claims_a_huge_size_are_refused_before_allocating_it():
    """The decompressor allocates the size a frame's header declares: a corrupt one is a
    WireError, not a MemoryError."""
    header = struct.pack("<I", 0xFD2FB528) + bytes([0xE0]) + struct.pack("<Q", 2**62)  # 8-byte content size
    block = ((1 << 3) | 1).to_bytes(3, "little")  # one raw byte, the last block
    with pytest.raises(wire.WireError, match="declare"):
        wire.decode_frames(header + block + b"\0", 1, (3, 84, 84))


def test_frames_round_trip_and_compress():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (3, 32, 32), dtype=np.uint8)
    moved = base.copy()
    moved[:, :4] = 255 - moved[:, :4]  # a small part changes; wrapping deltas included
    frames = np.stack([base, base, moved, moved])
    blob = wire.encode_frames(frames)
    np.testing.assert_array_equal(wire.decode_frames(blob, 4, (3, 32, 32)), frames)
    assert len(blob) < frames.nbytes * 0.5  # unchanged pixels cost ~nothing
    with pytest.raises(wire.WireError, match="expected"):
        wire.decode_frames(blob, 3, (3, 32, 32))
    with pytest.raises(wire.WireError, match="decompress"):
        wire.decode_frames(b"not zstd", 1, (3, 32, 32))


def test_arrays_and_tensors():
    a = np.arange(6, dtype="<f4").reshape(2, 3)
    np.testing.assert_array_equal(wire.array(a.tobytes(), "<f4", (2, 3)), a)
    with pytest.raises(wire.WireError, match="expected"):
        wire.array(a.tobytes(), "<f4", (3, 3))
    state = {"w": torch.randn(4, 5), "n": torch.tensor([3], dtype=torch.int64)}
    back = wire.unpack_tensors(wire.pack_tensors(state))
    assert back.keys() == state.keys()
    for k in state:
        assert torch.equal(back[k], state[k]) and back[k].dtype == state[k].dtype
    with pytest.raises(wire.WireError):
        wire.unpack_tensors({"w": ["<f4", [2], "notbytes"]})


def test_keys_live_under_the_run_prefix():
    k = wire.Keys("run-1")
    for key in (k.insert(3), k.ack(3), k.sample, k.intrinsic, k.replay_stats, k.weights, k.weights_latest,
                k.eval_weights, k.eval_weights_latest,
                k.actor_status(3), k.eval_result, k.stop, k.alive("actor", 3, 9)):
        assert key.startswith("nasa/run-1/")
    assert k.parse_alive(k.alive("actor", 3, 9)) == ("actor", "3", 9)
    assert k.parse_alive(k.alive("learner", 0)) == ("learner", "0", None)
    with pytest.raises(ValueError):
        wire.Keys("bad/id")
    with pytest.raises(wire.WireError):
        k.parse_alive("nasa/other/alive/actor/1/2")


def test_non_finite_float_fields_are_refused():
    for bad in (math.nan, math.inf):
        with pytest.raises(wire.WireError, match="steps_per_s"):
            wire.decode(wire.encode(wire.ActorStatus(0, 1, 2, 3, 4, bad, [])), wire.ActorStatus)


def test_weights_of_a_resumed_learner_are_newer():
    old = wire.Weights(epoch=10, version=500, env_steps=0, tensors={})
    resumed = wire.Weights(epoch=20, version=400, env_steps=0, tensors={})
    assert wire.newer_weights(old, None)
    assert wire.newer_weights(resumed, (10, 500))
    assert not wire.newer_weights(old, (20, 400))
    assert not wire.newer_weights(wire.Weights(10, 499, 0, {}), (10, 500))
