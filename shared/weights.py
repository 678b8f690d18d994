"""The weights subscriber of the processes that act: actors and the evaluator.

The learner publishes the policy's weights every few updates (latest wins) and
answers `learner/weights/latest` for a process that just started. The
subscriber only parks the newest message; the acting loop loads it between
steps (`maybe_load`), so acting never waits for weights. (epoch, version)
orders weights across learner restarts, so an older message never replaces a
newer one.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack

import zenoh

from shared import wire
from shared.agents import Agent


class WeightsSubscriber:
    def __init__(self, agent: Agent, on_invalid: Callable[[str], None]) -> None:
        self.agent = agent
        self.on_invalid = on_invalid
        self.version: int | None = None  # None until the first weights are loaded
        self.env_steps = 0  # the learner's env-step count when it published them
        self._held: tuple[int, int] | None = None
        self._pending: bytes | None = None
        self._stack = ExitStack()

    def offer(self, data: bytes) -> None:
        """Park a weights message (called from Zenoh's thread); the newest offered wins."""
        self._pending = data

    def maybe_load(self) -> bool:
        """Load the parked message if it is newer than what the agent holds; True if it loaded."""
        data, self._pending = self._pending, None
        if data is None:
            return False
        try:
            msg = wire.decode(data, wire.Weights)
            if not wire.newer_weights(msg, self._held):
                return False
            self.agent.load_policy_state_dict(wire.unpack_tensors(msg.tensors))
        except Exception as err:  # noqa: BLE001 -- torch's RuntimeError on bad shapes, and the unforeseen
            self.on_invalid(f"weights: {err}")
            return False
        self._held = (msg.epoch, msg.version)
        self.version = msg.version
        self.env_steps = max(self.env_steps, msg.env_steps)
        return True

    def subscribe(self, session: zenoh.Session, keys: wire.Keys) -> WeightsSubscriber:
        """Listen for published weights and ask the learner for its latest (a process that just started)."""
        self._stack.enter_context(session.declare_subscriber(keys.weights, self._on_sample))
        session.get(keys.weights_latest, self._on_reply, timeout=10.0)
        return self

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> WeightsSubscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.offer(sample.payload.to_bytes())

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None and self._pending is None and self._held is None:
            self.offer(reply.ok.payload.to_bytes())
