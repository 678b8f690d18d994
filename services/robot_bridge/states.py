"""The bridge's safety states, by name: what `status()` reports and an e-stop's answer carries.

Standard library only: `operate estop`/`rearm` judge an answer by them without loading the servo
driver, so confirming a stop never depends on more than the wire."""

from __future__ import annotations

from enum import StrEnum


class State(StrEnum):
    READY = "ready"
    ESTOP = "estop"
    RECOVERING = "recovering"
    WAITING_FOR_OPERATOR = "waiting_for_operator"


REARMED = (State.RECOVERING, State.READY)
"""The states that show a re-arm took effect: homing (the state the re-arm sets) or done. After a
re-arm, `waiting_for_operator` is a recovery that failed, and `estop` a later e-stop."""
