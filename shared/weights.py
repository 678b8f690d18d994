"""The weights subscriber of the processes that act: actors and the evaluator.

The learner publishes the policy's weights every few updates (latest wins) and
answers `learner/weights/latest` for a process that just started; the
evaluator's weights, once per evaluation period, go the same way on
`learner/eval_weights`. The
subscriber only parks the newest message; the acting loop loads it between
steps (`maybe_load`), so acting never waits for weights. (epoch, version)
orders weights across learner restarts, so an older message never replaces a
newer one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import ExitStack

import zenoh

from shared import wire
from shared.agents import Agent

# Until a process holds weights it asks for the latest again this often: a message published
# while its subscription was still reaching the router, and a query answered before the learner
# held any, would otherwise leave it waiting for the next publish (the evaluator's come once
# per evaluation period).
ASK_AGAIN_S = 1.0


class WeightsSubscriber:
    def __init__(self, agent: Agent, on_invalid: Callable[[str], None], steps: int | None = None) -> None:
        """`steps`: the run's step budget; weights claiming a learner count far beyond it are refused,
        as the largest count seen is kept (it ends the actor's warm-up, sets the evaluator's step)."""
        self.agent = agent
        self.on_invalid = on_invalid
        self.bounds = wire.Bounds(steps=steps)
        self.version: int | None = None  # None until the first weights are loaded
        self.env_steps = 0  # the learner's env-step count when it published them
        self._held: tuple[int, int] | None = None
        self._pending: bytes | None = None
        self._stack = ExitStack()
        self._ask: Callable[[], None] | None = None  # asks the learner for its latest (once subscribed)
        self._asked_at = 0.0

    def offer(self, data: bytes) -> None:
        """Park a weights message (called from Zenoh's thread); the newest offered wins."""
        self._pending = data

    def maybe_load(self) -> bool:
        """Load the parked message if it is newer than what the agent holds; True if it loaded."""
        data, self._pending = self._pending, None
        if data is None:
            now = time.monotonic()
            if self._held is None and self._ask is not None and now - self._asked_at > ASK_AGAIN_S:
                self._asked_at = now
                self._ask()
            return False
        try:
            msg = wire.decode(data, wire.Weights, self.bounds)
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

    def subscribe(self, session: zenoh.Session, key: str, latest: str) -> WeightsSubscriber:
        """Listen for the weights published on `key` and ask the learner for its latest (`latest`:
        a process that just started)."""
        self._stack.enter_context(session.declare_subscriber(key, self._on_sample))
        self._ask = lambda: session.get(latest, self._on_reply, timeout=10.0)
        self._asked_at = time.monotonic()
        self._ask()
        return self

    @property
    def epoch(self) -> int | None:
        """The epoch (the learner's incarnation) of the weights held; None before any."""
        return None if self._held is None else self._held[0]

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
