"""Issue 14: a fuzzer against a running system on loopback. For every key the services declare in
shared/wire.py it sends malformed messages (random bytes, another schema version or type, a missing
field, a giant payload with congestion control BLOCK) and well-formed messages with bad values, field
by field (wrong types, NaN and inf, negative and huge integers up to 2**64, wrong shapes and dtypes,
strings where numbers go). Then every process must be the one it was, the invalid counters must have
risen, training must go on, and nothing non-finite may have reached the store, the weights or the
checkpoint. It prints how many distinct messages it sent per key."""

from __future__ import annotations

import math
import os
import random
import threading
from collections.abc import Iterator

import msgpack
import numpy as np
import pytest
import torch
import zenoh
from system_harness import System

from services.learner.core import all_finite
from shared import wire
from shared.envs import EnvSpec
from shared.replay.store import open_store
from shared.run_config import read_folder

pytestmark = pytest.mark.system

FAKE_ACTOR = 4242  # inserts and statuses under an id no real actor has
BAD_SCALARS = ["x", None, math.nan, math.inf, -math.inf, -1, -(2**63), 2**62, 2**63, 2**64 - 1, 1.5, True,
               [1, 2], {"a": 1}, b"\x00\x01"]
GIANT = 4 << 20


def _f4(value: float, n: int) -> bytes:
    return np.full(n, value, "<f4").tobytes()


def _body(msg: wire.Message) -> dict:
    return msgpack.unpackb(wire.encode(msg), raw=False)


def _pack(body: object) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def valid_messages(spec: EnvSpec) -> dict[type, wire.Message]:
    """One well-formed message of each type, whose fields the fuzzer spoils one at a time."""
    n, a = 4, spec.action_dim
    frames = wire.encode_frames(np.zeros((n, *spec.frame_shape), np.uint8))
    first = wire.encode_frames(np.zeros((1, *spec.frame_shape), np.uint8))
    c, h, w = spec.frame_shape
    window = [n, c * (spec.frame_stack + 1), h, w]
    return {
        wire.TransitionBatch: wire.TransitionBatch(
            FAKE_ACTOR, 1, 0, 0, n, list(spec.frame_shape), frames, first, _f4(0.5, n * a), _f4(1, n),
            _f4(1, n), bytes(n), np.zeros(n, "<i8").tobytes()),
        wire.InsertAck: wire.InsertAck(0, 1, 10),
        wire.SampleRequest: wire.SampleRequest(4, 0.1),
        wire.UnscoredRequest: wire.UnscoredRequest(0, 4),
        wire.SampleReply: wire.SampleReply(True, "", 10, n, window, bytes(math.prod(window)), _f4(0, n * a),
                                           _f4(0, n), _f4(0, n), _f4(1, n), np.zeros(n, "<i8").tobytes(),
                                           np.zeros(n, "<i8").tobytes()),
        wire.SetIntrinsic: wire.SetIntrinsic(np.zeros(2, "<i8").tobytes(), _f4(0.5, 2)),
        wire.ReplayStats: wire.ReplayStats(1, 1, 1, 1, 1, 0, 0, False),
        wire.Weights: wire.Weights(1, 1, 0, {"actor.w": ["<f4", [2], _f4(0.5, 2)]}),
        wire.ActorStatus: wire.ActorStatus(FAKE_ACTOR, 1, 1, 1, 1, 1.0, [[1.0, 10]]),
        wire.EvalResult: wire.EvalResult(0, 0, [1.0]),
        wire.RunConfigMsg: wire.RunConfigMsg({}, "0"),
        wire.Stop: wire.Stop("fuzz"),
    }


def bad_bytes(name: str, value: bytes) -> Iterator[bytes]:
    """Spoilt payloads of a bytes field: wrong sizes, and right sizes with bad values."""
    yield from (b"", b"\x00" * 3, os.urandom(64), value + b"\x00", os.urandom(1 << 20))
    if len(value) % 4 == 0 and len(value):
        for v in (math.nan, math.inf, -math.inf, 3e38, -5.0, 2.0):
            yield _f4(v, len(value) // 4)
    if len(value) % 8 == 0 and len(value):
        for v in (-1, 2**62, -(2**63)):
            yield np.full(len(value) // 8, v, "<i8").tobytes()


def variants(msg: wire.Message) -> Iterator[bytes]:
    """Every spoilt message of `msg`'s type: raw garbage, then field by field."""
    body = _body(msg)
    yield os.urandom(32)
    yield _pack([1, 2, 3])
    yield _pack({**body, "v": wire.SCHEMA_VERSION + 1})
    yield _pack({**body, "v": "3"})
    yield _pack({**body, "t": "not_a_type"})
    yield os.urandom(GIANT)
    for name, value in body.items():
        if name in ("v", "t"):
            continue
        rest = {k: v for k, v in body.items() if k != name}
        yield _pack(rest)
        for bad in BAD_SCALARS:
            yield _pack({**body, name: bad})
        if isinstance(value, bytes):
            for bad in bad_bytes(name, value):
                yield _pack({**body, name: bad})
        if isinstance(value, list):
            for bad in ([], [1] * 9, ["3", 1, 1], [-1, 2, 2], [2**62, 2**62, 2**62, 2**62], [[1.0]]):
                yield _pack({**body, name: bad})
    if isinstance(msg, wire.Weights):
        for entry in (["<q9", [2], b"\0" * 8], ["<f4", [3], b"\0" * 8], ["<f4", [2], _f4(math.nan, 2)],
                      ["<f4", "2", b"\0" * 8], "x", ["<f4", [2]]):
            yield _pack({**body, "tensors": {"actor.w": entry}})
        yield _pack({**body, "tensors": {str(i): ["<f4", [1], b"\0" * 4] for i in range(1001)}})


def refused(payload: bytes, cls: type, bounds: wire.Bounds) -> bool:
    try:
        wire.decode(payload, cls, bounds)
    except wire.WireError:
        return True
    return False


def deep_bad(spec: EnvSpec, valid: dict) -> dict[type, list[bytes]]:
    """Messages that pass the wire checks and are refused deeper: a batch that continues no episode,
    scores for rows the replay does not hold, weights of the wrong shapes, or none."""
    batch = valid[wire.TransitionBatch]
    orphan = _body(batch) | {"start": 8, "first_frame": None}
    weights = valid[wire.Weights]
    return {
        wire.TransitionBatch: [_pack(orphan)],
        wire.SetIntrinsic: [wire.encode(wire.SetIntrinsic(np.full(2, 2**40, "<i8").tobytes(), _f4(0.5, 2)))],
        wire.Weights: [_pack(_body(weights) | {"epoch": 2**61}),
                       _pack(_body(weights) | {"epoch": 2**61, "tensors": {}})],
    }


def fuzz(session: zenoh.Session, keys: wire.Keys, spec: EnvSpec) -> dict[str, int]:
    """Send every variant to its key; returns how many distinct messages each key got."""
    bounds = wire.Bounds.of(spec)
    valid = valid_messages(spec)
    targets = {
        wire.TransitionBatch: ("put", keys.insert(FAKE_ACTOR)),
        wire.InsertAck: ("put", keys.ack(0)),
        wire.SampleRequest: ("get", keys.sample),
        wire.UnscoredRequest: ("get", keys.unscored),
        wire.SetIntrinsic: ("put", keys.intrinsic),
        wire.ReplayStats: ("put", keys.replay_stats),
        wire.Weights: ("put", keys.weights),
        wire.ActorStatus: ("put", keys.actor_status(FAKE_ACTOR)),
        wire.EvalResult: ("put", keys.eval_result),
        wire.Stop: ("put", keys.stop),
        wire.RunConfigMsg: ("get", keys.config),  # the replay answers; its payload is not read
    }
    extra = deep_bad(spec, valid)
    sent: dict[str, set[bytes]] = {}
    block = zenoh.CongestionControl.BLOCK
    for cls, (how, key) in targets.items():
        payloads = [p for p in variants(valid[cls]) if refused(p, cls, bounds)] + extra.get(cls, [])
        random.Random(0).shuffle(payloads)
        for p in payloads:
            if how == "put":
                session.put(key, p, congestion_control=block)
            else:
                for _ in session.get(key, payload=p, timeout=5.0, congestion_control=block):
                    pass
        sent[key.removeprefix(keys.prefix + "/")] = set(payloads)
        if cls is wire.Weights:  # the evaluator's weights: the same message on a key of its own
            for p in payloads:
                session.put(keys.eval_weights, p, congestion_control=block)
            sent[keys.eval_weights.removeprefix(keys.prefix + "/")] = set(payloads)
    for p in list(variants(valid[wire.Stop]))[:8]:  # the learner answers whatever the query holds
        for _ in session.get(keys.weights_latest, payload=p, timeout=5.0, congestion_control=block):
            pass
    sent["learner/weights/latest"] = set(list(variants(valid[wire.Stop]))[:8])
    sent["replay/sample (replies)"] = rogue_replies(session, keys, valid, bounds)
    return {k: len(v) for k, v in sent.items()}


def rogue_replies(session: zenoh.Session, keys: wire.Keys, valid: dict, bounds: wire.Bounds) -> set[bytes]:
    """A second queryable on replay/sample answering the learner's requests with bad SampleReplies
    (the learner takes the last reply it decodes, and refuses the request's answer if one is bad)."""
    pending = [p for p in variants(valid[wire.SampleReply]) if refused(p, wire.SampleReply, bounds)]
    sent: set[bytes] = set()
    done = threading.Event()

    def answer(query: zenoh.Query) -> None:
        if pending:
            p = pending.pop()
            query.reply(keys.sample, p)
            sent.add(p)
        else:
            done.set()
        query.drop()

    with session.declare_queryable(keys.sample, answer):
        done.wait(60.0)
    return sent


@pytest.mark.timeout(400)
def test_bad_messages_on_every_key_poison_nothing_and_stop_nothing(tmp_path):
    data = tmp_path / "run"
    system = System(data, actors=1, steps=1_000_000, evaluator=True,
                    extra=["--eval-every", "100000", "--checkpoint-every", "1000000"])
    try:
        before = system.wait_for("updates", lambda s: s["updates"] > 5, timeout=240)
        pids = {name: c.proc.pid for name, c in system.sup.children.items()}
        body = read_folder(data)
        spec = EnvSpec(tuple(body["spec"]["frame_shape"]), body["spec"]["frame_stack"],
                       body["spec"]["action_dim"])
        keys = wire.Keys(before["run_id"])
        session = zenoh.open(_client_config(system.endpoint))
        try:
            counts = fuzz(session, keys, spec)
            print("fuzz: distinct messages per key:", counts)
            after = system.wait_for(
                "training to go on and the invalid counters to rise",
                lambda s: s["updates"] > before["updates"] + 10
                and s["invalid_messages"] >= before["invalid_messages"] + 50
                and s["replay"]["invalid_messages"] >= before["replay"]["invalid_messages"] + 50,
                timeout=180)
            replies = session.get(keys.weights_latest, timeout=10.0)
            weights = [r.ok.payload.to_bytes() for r in replies if r.ok is not None]
        finally:
            session.close()
        assert all(n >= 8 for n in counts.values()) and len(counts) == 14, counts
        assert {name: c.proc.pid for name, c in system.sup.children.items()} == pids
        assert all(c.restarts == 0 and c.proc.poll() is None for c in system.sup.children.values())
        assert all(a["alive"] for a in after["actors"] if a["id"] != FAKE_ACTOR)
        assert weights and wire.decode(weights[0], wire.Weights, wire.Bounds.of(spec))  # finite
        assert after["nonfinite"]["skipped_updates"] == 0
    finally:
        system.close()
    state = torch.load(data / "learner" / "checkpoint.pt", weights_only=True)
    assert all_finite(state["agent"])
    _assert_store_finite(data, body)


def _client_config(endpoint: str) -> zenoh.Config:
    import json

    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return config


def _assert_store_finite(data, body: dict) -> None:  # noqa: ANN001
    from shared.run_config import RunConfig, config_from_dict

    run = RunConfig(config_from_dict({k: v for k, v in body.items() if k != "spec"}),
                    EnvSpec(tuple(body["spec"]["frame_shape"]), body["spec"]["frame_stack"],
                            body["spec"]["action_dim"]))
    store = open_store(run, data / "replay")
    try:
        n = store.num_inserted
        rows = store.get(np.arange(max(0, n - len(store)), n))
        assert n > 0 and np.isfinite(rows["action"]).all() and (np.abs(rows["action"]) <= 1).all()
        assert np.isfinite(rows["reward"]).all() and (np.abs(rows["reward"]) <= 1e3).all()
        assert ((rows["discount"] >= 0) & (rows["discount"] <= 1)).all()
        assert not np.isinf(rows["intrinsic"]).any()
    finally:
        store.close()
