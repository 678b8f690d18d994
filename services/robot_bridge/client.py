"""`BridgeEnv`: a remote gripper (or stand-in) behind a robot bridge, as a raw environment layer.

It has the raw layer's interface (`reset`/`step` -> (frame, reward, discount, last), `action_dim`,
`image_size`, `rng_state`), so `shared.envs.FrameStack` stacks its frames like a local task's and
the actor above it does not change. The bridge draws targets and reset angles itself, so the
client's random state is empty. A bridge that does not answer (gone, or refusing a reset during
an e-stop or fault) raises `BridgeUnavailable`: the actor pauses and starts a new episode later.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import zenoh

from shared import wire

SPEC_RETRY_S = 2.0


class BridgeUnavailable(RuntimeError):
    """The bridge did not answer, or refused (e-stop, fault, waiting for an operator)."""


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
        return any(r.ok is not None for r in self.session.liveliness().get(self.keys.alive, timeout=5.0))

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

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        r = self._ask(self.keys.reset, wire.BridgeReset(self.client), wire.BridgeReply)
        if not r.ok:
            raise BridgeUnavailable(f"bridge {self.keys.prefix} refused a reset: {r.reason}")
        self.episode, self._step = r.episode, 0
        return self._frame(r), 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        payload = np.asarray(action, dtype="<f4").tobytes()
        msg = wire.BridgeStep(self.client, self.episode, self._step, payload)
        r = self._ask(self.keys.step, msg, wire.BridgeReply)
        self._step += 1
        return self._frame(r), r.reward, r.discount, r.last

    def _frame(self, r: wire.BridgeReply) -> np.ndarray:
        self.info = r.info
        if tuple(r.frame_shape) != self.frame_shape:
            announced = list(self.frame_shape)
            raise wire.WireError(f"frame shape {r.frame_shape}, the bridge announced {announced}")
        return wire.array(r.frame, "u1", self.frame_shape)

    def _ask(self, key: str, msg: wire.Message, cls: type[wire.M], timeout_s: float | None = None) -> wire.M:
        timeout_s = self.timeout_s if timeout_s is None else max(timeout_s, 0.1)
        try:
            replies = self.session.get(key, payload=wire.encode(msg), timeout=timeout_s)
            for reply in replies:
                if reply.ok is not None:
                    return wire.decode(reply.ok.payload.to_bytes(), cls)
                raise BridgeUnavailable(f"bridge {self.keys.prefix}: {reply.err.payload.to_bytes().decode()}")
        except zenoh.ZError as e:
            raise BridgeUnavailable(f"bridge {self.keys.prefix}: {e}") from e
        raise BridgeUnavailable(f"bridge {self.keys.prefix} did not answer within {timeout_s} s")
