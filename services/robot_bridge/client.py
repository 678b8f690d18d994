"""`BridgeEnv`: a remote gripper (or stand-in) behind a robot bridge, as a raw environment layer.

It has the raw layer's interface (`reset`/`step` -> (frame, reward, discount, last), `action_dim`,
`image_size`, `rng_state`), so `shared.envs.FrameStack` stacks its frames like a local task's and
the actor above it does not change. The bridge draws targets and reset angles itself, so the
client's random state is empty. A bridge that does not answer (gone, or refusing a reset during
an e-stop or fault) raises `BridgeUnavailable`: the actor pauses and starts a new episode later;
`BridgeHeld` when the refusal is that another client holds the gripper (`hold.py`).
`BridgePresence` follows the bridge's liveliness token, so an actor knows at once that its bridge
went; `fault_state` names the bridge's safety state in one word for the learner's /status.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from services.robot_bridge import xl320
from shared import wire
from shared.envs import EnvUnavailable
from shared.zenoh_session import token_up

SPEC_RETRY_S = 2.0
BRIDGE_LOST = "bridge_lost"


class BridgeUnavailable(EnvUnavailable):
    """The bridge did not answer, or refused (e-stop, fault, waiting for an operator)."""


class BridgeHeld(BridgeUnavailable):
    """The bridge refused: another client holds the gripper (`holder` names it)."""

    def __init__(self, message: str, holder: str) -> None:
        super().__init__(message)
        self.holder = holder


def client_name(role: str, run_id: str) -> str:
    """Who a client is to a bridge: its role (`actor 3`, `evaluator`), run and host. Not its pid:
    the same actor restarted on its host gets the gripper back at once, and any other client waits."""
    return f"{role} of run {run_id} on {socket.gethostname()}"


def fault_state(info: dict) -> str:
    """The bridge's safety state (a reply's info map) in one word: `ok`, the interlocks' state
    (`estop`, `recovering`, `waiting_for_operator`), `torque_off` (the watchdog's), or the first
    hardware error of the last step (`overload`, `overheating`, `input_voltage`); `held` when the
    bridge refused because another client holds its gripper (this client cannot use it at all)."""
    if info.get("holder"):
        return "held"
    safety = info.get("safety") or {}
    state = safety.get("state", "ready")
    if state != "ready":
        return str(state)
    if safety.get("watchdog") == "torque_off":
        return "torque_off"
    for names in (safety.get("errors") or {}).values():
        known = [n for n in xl320.ERROR_NAMES.values() if n in names]
        if known:
            return known[0].replace(" ", "_")
    return "ok"


class BridgePresence:
    """Whether a bridge's liveliness token is present, from a liveliness subscriber (with history,
    so a bridge already up counts); a context manager."""

    def __init__(self, session: zenoh.Session, bridge_id: str | int) -> None:
        self.session = session
        self.keys = wire.BridgeKeys(bridge_id)
        self._present = threading.Event()
        self._subscriber = None

    @property
    def present(self) -> bool:
        return self._present.is_set()

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._present.set()
        else:
            self._present.clear()

    def wait(self, stop: Callable[[], bool], poll_s: float = 0.2) -> bool:
        """Block until the bridge is present (True) or `stop()` (False)."""
        while not stop():
            if self._present.wait(poll_s):
                return True
        return False

    def __enter__(self) -> BridgePresence:
        self._subscriber = self.session.liveliness().declare_subscriber(
            self.keys.alive, self._on_token, history=True)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None


class BridgeEnv:
    def __init__(self, session: zenoh.Session, bridge_id: str | int, client: str = "actor",
                 timeout_s: float = 30.0) -> None:
        self.session = session
        self.keys = wire.BridgeKeys(bridge_id)
        self.client = client
        self.timeout_s = timeout_s
        spec = self._wait_for_spec(time.monotonic() + timeout_s)
        self.task = spec.task
        self.action_dim = spec.action_dim
        self.frame_shape = tuple(spec.frame_shape)
        self.image_size = self.frame_shape[1]
        self.episode = -1
        self._step = 0
        self._rewind = False
        self.info: dict = {}

    def _wait_for_spec(self, deadline: float) -> wire.BridgeSpec:
        """Ask until the bridge answers: it may start after the actor, or be declaring its keys."""
        while True:
            left = deadline - time.monotonic()
            try:
                request = wire.BridgeSpecRequest()
                return self._ask(self.keys.spec, request, wire.BridgeSpec, min(SPEC_RETRY_S, left))
            except BridgeUnavailable:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.1)

    def alive(self) -> bool:
        """Whether the bridge's liveliness token is up."""
        return token_up(self.session, self.keys.alive, timeout_s=5.0)

    def wait_alive(self, stop: Callable[[], bool], poll_s: float = 0.5) -> bool:
        """Block until the bridge is up again (True) or `stop()` (False): how an actor pauses."""
        while not stop():
            if self.alive():
                return True
            time.sleep(poll_s)
        return False

    def rng_state(self) -> dict:
        return {}

    def set_rng_state(self, state: dict) -> None:
        pass  # the bridge owns the draws of targets and reset angles

    def rewind_draws(self) -> None:
        """The next reset asks the bridge to put its draws back where they stood when it started
        (its own RNG state: the client cannot hold it), for evaluations of the same episodes."""
        self._rewind = True

    def fault(self) -> str:
        """The bridge's safety state after its last reply (`fault_state`)."""
        return fault_state(self.info)

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        msg = wire.BridgeReset(self.client, self._rewind, os.getpid())
        r = self._ask(self.keys.reset, msg, wire.BridgeReply)
        if not r.ok:
            self.info = r.info  # why: the safety state of a refusal (e-stop, waiting for an operator)
            raise self._refused("a reset", r)
        self._rewind = False
        self.episode, self._step = r.episode, 0
        return self._frame(r), 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        payload = np.asarray(action, dtype="<f4").tobytes()
        msg = wire.BridgeStep(self.client, self.episode, self._step, payload, os.getpid())
        r = self._ask(self.keys.step, msg, wire.BridgeReply)
        if not r.ok:  # not executed (an e-stop, a stale step): the episode is abandoned, nothing stored
            self.info = r.info
            raise self._refused("a step", r)
        self._step += 1
        return self._frame(r), r.reward, r.discount, r.last

    def _refused(self, what: str, r: wire.BridgeReply) -> BridgeUnavailable:
        message = f"bridge {self.keys.prefix} refused {what}: {r.reason}"
        holder = r.info.get("holder")
        return BridgeHeld(message, str(holder)) if holder else BridgeUnavailable(message)

    def _frame(self, r: wire.BridgeReply) -> np.ndarray:
        self.info = r.info
        if tuple(r.frame_shape) != self.frame_shape:
            announced = list(self.frame_shape)
            raise BridgeUnavailable(f"bridge {self.keys.prefix}: a frame of shape {r.frame_shape}, "
                                    f"it announced {announced}")
        try:
            return wire.array(r.frame, "u1", self.frame_shape)
        except wire.WireError as err:
            raise BridgeUnavailable(f"bridge {self.keys.prefix}: a malformed frame: {err}") from err

    def _ask(self, key: str, msg: wire.Message, cls: type[wire.M], timeout_s: float | None = None) -> wire.M:
        timeout_s = self.timeout_s if timeout_s is None else max(timeout_s, 0.1)
        try:
            replies = self.session.get(key, payload=wire.encode(msg), timeout=timeout_s)
            for reply in replies:
                if reply.ok is not None:
                    # A reply it cannot read is the bridge's fault, not this process's: the actor pauses
                    # and abandons the episode, as for a bridge that does not answer, and is not restarted.
                    try:
                        return wire.decode(reply.ok.payload.to_bytes(), cls)
                    except wire.WireError as err:
                        raise BridgeUnavailable(f"bridge {self.keys.prefix}: a malformed reply: {err}") \
                            from err
                raise BridgeUnavailable(f"bridge {self.keys.prefix}: {reply.err.payload.to_bytes().decode()}")
        except zenoh.ZError as e:
            raise BridgeUnavailable(f"bridge {self.keys.prefix}: {e}") from e
        raise BridgeUnavailable(f"bridge {self.keys.prefix} did not answer within {timeout_s} s")
