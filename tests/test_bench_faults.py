"""bench.faults: the bad-message sender stops with its phase, however the phase ends."""

from __future__ import annotations

import threading

import pytest

from bench import faults


class Session:
    def __init__(self) -> None:
        self.puts = 0

    def put(self, key: str, payload: bytes, congestion_control: object = None) -> None:
        self.puts += 1


class InterruptedSystem:
    """A system whose second status read is interrupted, as a Ctrl-C in the phase's sleep is."""

    def __init__(self) -> None:
        self.reads = 0

    def status(self) -> dict:
        self.reads += 1
        if self.reads == 2:
            raise KeyboardInterrupt
        return {"wall_s": 0.0, "env_steps": 0, "updates": 0}


def test_the_sender_stops_when_the_phase_is_interrupted(monkeypatch):
    pytest.importorskip("zenoh")
    before = set(threading.enumerate())
    session, sent = Session(), [0]
    with pytest.raises(KeyboardInterrupt):
        faults.fuzzed_phase(InterruptedSystem(), session, [("put", "k", b"x")], 1000.0, 0.3, sent)
    assert set(threading.enumerate()) - before == set()  # nothing left to keep the process alive
    assert sent[0] == session.puts > 0
