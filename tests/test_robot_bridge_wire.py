"""The robot bridge's wire messages: round trips, registration, validation."""

import msgpack
import pytest

from shared import wire

BRIDGE_MESSAGES = [
    wire.BridgeSpecRequest(),
    wire.BridgeSpec("gripper-valve", 4, [3, 84, 84]),
    wire.BridgeReset("actor-0"),
    wire.BridgeReset("evaluator", rewind=True),
    wire.BridgeStep("actor-0", 2, 7, b"\0" * 16),
    wire.BridgeReset("actor 3 of run r on host", pid=1234),
    wire.BridgeStep("actor 3 of run r on host", 2, 7, b"\0" * 16, pid=1234),
    wire.BridgeReply(True, "", 2, 8, [3, 2, 2], b"f" * 12, -0.25, 1.0, False, True,
                     {"valve_angle": 1.5, "positions": [512, 600], "safety": {"state": "ready"}}),
    wire.BridgeEStop(True, "button"),
    wire.BridgeEStop(False, "re-arm", request="0123abcd"),
    wire.BridgeEStopAck("0123abcd", True, "estop", [3], "host pid 12"),
]


def test_bridge_messages_round_trip_and_are_registered() -> None:
    for m in BRIDGE_MESSAGES:
        assert wire.decode(wire.encode(m), type(m)) == m
        assert wire.MESSAGES[m.TYPE] is type(m)


def test_bridge_messages_are_validated() -> None:
    body = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_step", "client": "a", "episode": "x",
                          "step": 0, "action": b""})
    with pytest.raises(wire.WireError, match="episode"):
        wire.decode(body, wire.BridgeStep)
    no_rewind = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_reset", "client": "a"})
    assert wire.decode(no_rewind, wire.BridgeReset).rewind is False  # optional: a plain reset
    assert wire.decode(no_rewind, wire.BridgeReset).pid == 0  # an older client sends none
    for pid in ("1234", True, -1, 2**63, 1.5):  # a pid is a count: no text, bool, negative or float
        bad_pid = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_reset", "client": "a", "pid": pid})
        with pytest.raises(wire.WireError, match="pid"):
            wire.decode(bad_pid, wire.BridgeReset)
    bad_rewind = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_reset", "client": "a", "rewind": 1})
    with pytest.raises(wire.WireError, match="rewind"):
        wire.decode(bad_rewind, wire.BridgeReset)
    no_engage = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_estop", "reason": "x"})
    with pytest.raises(wire.WireError, match="missing field 'engage'"):
        wire.decode(no_engage, wire.BridgeEStop)


def test_bridge_keys_name_the_bridge() -> None:
    keys = wire.BridgeKeys(3)
    assert (keys.reset, keys.step, keys.estop, keys.alive) == (
        "nasa/bridge/3/reset", "nasa/bridge/3/step", "nasa/bridge/3/estop", "nasa/bridge/3/alive",
    )
    with pytest.raises(ValueError):
        wire.BridgeKeys("a/b")


def test_an_estop_ack_names_a_state_and_servo_ids_or_is_refused() -> None:
    """The operator is told what an e-stop's answer holds: one whose servos are no servo ids or whose
    state is no state name is refused as malformed, not printed."""
    good = msgpack.unpackb(wire.encode(wire.BridgeEStopAck("r", True, "estop", [3, 252], "h pid 1")))
    assert wire.decode(msgpack.packb(good), wire.BridgeEStopAck).unreached == [3, 252]
    for field, bad in (("unreached", [[1.0]]), ("unreached", ["3"]), ("unreached", [-1]),
                       ("unreached", [253]), ("unreached", [True]), ("unreached", list(range(254)) + [0]),
                       ("state", ""), ("state", "x" * 65)):
        with pytest.raises(wire.WireError, match=field):
            wire.decode(msgpack.packb({**good, field: bad}), wire.BridgeEStopAck)
