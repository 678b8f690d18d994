"""The bridge's Zenoh side: serves one gripper (or its stand-in) as reset/step queryables.

Zenoh callbacks only queue work: one worker thread steps the environment, so an e-stop message
is handled at once even while a step is in flight (the hardware's `SafeFingers.estop` then wins
over that step). Every reply carries the raw frame, never a stack: the client stacks.
For the real gripper, a second thread polls the watchdog.
"""

from __future__ import annotations

import os
import queue
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import zenoh

from services.robot_bridge.hold import DEFAULT_HOLD_S, ClientHold
from services.robot_bridge.safety import Refused
from shared import wire
from shared.text import clip

WATCHDOG_POLL_S = 0.1
# An e-stop's reason goes into every refusal after it ("e-stop: <reason>"), which the client reads
# only within wire.MAX_TEXT: a longer one (an operator's, or a garbled message's error quoting
# what it was sent) is cut, so the actor still hears that the bridge is e-stopped.
ESTOP_REASON_CHARS = 512


class BridgeServer:
    """One environment behind the bridge's keys; `serve()` declares them for as long as it runs."""

    def __init__(self, session: zenoh.Session, bridge_id: str | int, env: Any, task: str,
                 log: Callable[[str], None] = print, hold_s: float = DEFAULT_HOLD_S) -> None:
        self.session = session
        self.keys = wire.BridgeKeys(bridge_id)
        self.env = env
        self.task = task
        self.log = log
        self.frame_shape = (3, env.image_size, env.image_size)
        self._start_draws = env.rng_state()  # where a `rewind` puts the draws back
        self.episode = -1
        self.step_index = 0
        self._estopped = threading.Event()  # the stand-in's e-stop; the hardware's is its interlocks'
        self.estop_reason = ""
        self.invalid = 0
        self._done = True
        self._frame = np.zeros(self.frame_shape, np.uint8)
        self._work: queue.Queue[tuple[zenoh.Query, str, bytes]] = queue.Queue()
        self._stop = threading.Event()
        self._safety = getattr(env, "fingers", None)  # the real gripper's interlocks, if any
        self.hold = ClientHold(hold_s, log)  # the client served; the e-stop key is anyone's

    # -- e-stop ---------------------------------------------------------------------------------
    @property
    def estopped(self) -> bool:
        """One flag, never two that drift: the interlocks' for the real gripper (e-stops and
        re-arms racing each other end where the interlocks end), the server's for the stand-in."""
        return self._safety.estopped if self._safety is not None else self._estopped.is_set()

    def estop(self, reason: str) -> list[int]:
        """Idempotent: the flag first, then the hardware's torque-off (which wins over a step).
        Returns when it holds, with the servos the torque-off did not reach."""
        reason = clip(reason, ESTOP_REASON_CHARS)
        self.estop_reason = reason
        unreached: list[int] = []
        if self._safety is not None:
            unreached = self._safety.estop()
        else:
            self._estopped.set()
        missed = f" (torque-off did not reach servos {unreached})" if unreached else ""
        self.log(f"e-stop: {reason}{missed}")
        return unreached

    def safety_status(self) -> dict:
        """The interlocks' snapshot (the stand-in's: ready or estop), `estop` whenever the flag is set."""
        safety = self._safety.status() if self._safety is not None else {"state": "ready"}
        if self.estopped:
            safety["state"] = "estop"
        return safety

    def rearm(self) -> None:
        """Clear the e-stop; the real gripper then recovers and homes (which takes a while)."""
        self._release()
        self._recover()

    def _release(self) -> None:
        if self._safety is not None:
            self._safety.release()
        else:
            self._estopped.clear()
        self.log("re-armed")

    def _recover(self) -> None:
        if self._safety is not None:
            self._safety.recover()

    # -- requests -------------------------------------------------------------------------------
    def handle_spec(self) -> wire.BridgeSpec:
        return wire.BridgeSpec(self.task, int(self.env.action_dim), list(self.frame_shape))

    def handle_reset(self, msg: wire.BridgeReset) -> wire.BridgeReply:
        held = self.hold.refusal(msg.client, msg.pid, takes=True)
        if held is not None:
            return self._refusal(held, holder=self.hold.holder())
        if self.estopped:
            return self._refusal(f"e-stop: {self.estop_reason}")
        start = time.perf_counter()
        if msg.rewind:
            self.env.set_rng_state(self._start_draws)
        try:
            frame, _, _, _ = self.env.reset()
        except Refused as e:
            return self._refusal(str(e))
        self.episode += 1
        self.step_index, self._done, self._frame = 0, False, frame
        return self._reply(frame, 0.0, 1.0, True, False, time.perf_counter() - start, "")

    def handle_step(self, msg: wire.BridgeStep) -> wire.BridgeReply:
        action = wire.array(msg.action, "<f4", (int(self.env.action_dim),))
        held = self.hold.refusal(msg.client, msg.pid, takes=False)
        if held is not None:  # another client's episode is the live one: it goes on
            return self._refusal(held, holder=self.hold.holder())
        # Refused, not answered as a step: a transition that never ran must not reach the replay.
        # A stale step (one sent again, or its client's from before it restarted) leaves the live
        # episode as it is.
        if msg.episode != self.episode or msg.step != self.step_index or self._done:
            return self._refusal(f"stale step (episode {msg.episode} step {msg.step}): reset first")
        if self.estopped:
            self._done = True
            return self._refusal(f"e-stop: {self.estop_reason}")
        start = time.perf_counter()
        frame, reward, discount, last = self.env.step(np.asarray(action, np.float64))
        env_s = time.perf_counter() - start
        if self.estopped:  # pressed during the step: whatever it did, the episode ends here
            last = True
        self.step_index += 1
        self._done, self._frame = last, frame
        return self._reply(frame, float(reward), float(discount), False, bool(last), env_s, "")

    def _info(self, env_s: float, reason: str) -> dict:
        info = self.env.info() if hasattr(self.env, "info") else {
            "valve_angle": float(self.env.valve_angle),
            "target_angle": float(self.env.target_angle),
            "positions": self.env.servo_positions().tolist(),
            "truncated": bool(reason),
            "reason": reason,
            "safety": {"state": "ready"},
        }
        if self.estopped:
            info["safety"] = {**info.get("safety", {}), "state": "estop"}
            info["reason"] = info.get("reason") or reason
        info["env_s"] = env_s
        return info

    def _reply(self, frame: np.ndarray, reward: float, discount: float, first: bool, last: bool,
               env_s: float, reason: str) -> wire.BridgeReply:
        data = np.ascontiguousarray(frame).tobytes()
        return wire.BridgeReply(
            True, reason, self.episode, self.step_index, list(frame.shape), data,
            reward, discount, first, last, self._info(env_s, reason),
        )

    def _refusal(self, reason: str, holder: str = "") -> wire.BridgeReply:
        """`holder`: the client that holds the gripper, when that is why (the client tells this
        refusal from a fault by it)."""
        safety = self.safety_status()
        info = {"reason": reason, "safety": safety, **({"holder": holder} if holder else {})}
        # Before the first episode (-1) the wire's episode is 0: -1 is no count, and the client would
        # take the refusal (an e-stop, an operator awaited) for a malformed reply.
        return wire.BridgeReply(False, reason, max(self.episode, 0), 0, list(self.frame_shape), b"", 0.0, 1.0,
                                False, False, info)

    # -- Zenoh ----------------------------------------------------------------------------------
    def _on_query(self, kind: str) -> Callable[[zenoh.Query], None]:
        def queue_it(query: zenoh.Query) -> None:
            payload = query.payload
            self._work.put((query, kind, payload.to_bytes() if payload is not None else b""))
        return queue_it

    def _on_estop(self, sample: zenoh.Sample) -> None:
        try:
            msg = wire.decode(sample.payload.to_bytes(), wire.BridgeEStop)
        except wire.WireError as err:
            # Fail safe: only an operator may send here, and a stop that cannot be read may still be
            # one; a re-arm that cannot be read is not taken (the operator hears no answer and asks
            # again).
            self.invalid += 1
            self.estop(f"an e-stop message that could not be read ({err})")
            return
        unreached: list[int] = []
        if msg.engage:
            unreached = self.estop(msg.reason)
        else:
            # Released here, in the order the messages came (an e-stop sent after it wins); the
            # homing takes time, so it runs on a thread of its own.
            self._release()
            threading.Thread(target=self._recover, name="rearm", daemon=True).start()
        # Told only now, once the stop holds: an operator who hears nothing knows it may not.
        ack = wire.BridgeEStopAck(msg.request, msg.engage, self.safety_status()["state"], unreached,
                                  f"{socket.gethostname()} pid {os.getpid()}", stand_in=self._safety is None)
        try:
            self.session.put(self.keys.estop_ack, wire.encode(ack))
        except Exception as err:  # noqa: BLE001 (the stop holds whether or not the answer goes out)
            self.log(f"could not acknowledge the e-stop message: {type(err).__name__}: {err}")

    def _answer(self, query: zenoh.Query, kind: str, payload: bytes) -> None:
        try:
            if kind == "spec":
                wire.decode(payload, wire.BridgeSpecRequest)
                reply: wire.Message = self.handle_spec()
            elif kind == "reset":
                reply = self.handle_reset(wire.decode(payload, wire.BridgeReset))
            else:
                reply = self.handle_step(wire.decode(payload, wire.BridgeStep))
            query.reply(query.key_expr, wire.encode(reply))
        except wire.WireError as err:
            self.invalid += 1
            query.reply_err(str(err).encode())
        except Exception as err:  # noqa: BLE001 (a camera or bus failure must not kill the bridge)
            self.log(f"{kind} failed: {type(err).__name__}: {err}")
            self._done = True  # the episode under way cannot go on
            query.reply_err(f"{kind} failed: {type(err).__name__}: {err}".encode())
        finally:
            query.drop()

    def _work_loop(self) -> None:
        while not self._stop.is_set():
            try:
                query, kind, payload = self._work.get(timeout=0.2)
            except queue.Empty:
                continue
            self._answer(query, kind, payload)

    def _watchdog_loop(self) -> None:
        while not self._stop.wait(WATCHDOG_POLL_S):
            try:
                self._safety.poll_watchdog()
            except Exception as err:  # noqa: BLE001 -- the watchdog must outlive any one poll
                self.log(f"watchdog poll failed: {type(err).__name__}: {err}")

    @contextmanager
    def serve(self) -> Iterator[BridgeServer]:
        s, k = self.session, self.keys
        threads = [threading.Thread(target=self._work_loop, name="bridge", daemon=True)]
        if self._safety is not None:
            threads.append(threading.Thread(target=self._watchdog_loop, name="watchdog", daemon=True))
        # Declared in this order on purpose: a client that got a spec answer (or sees the token)
        # finds reset, step and e-stop already declared.
        with (
            s.declare_queryable(k.reset, self._on_query("reset")),
            s.declare_queryable(k.step, self._on_query("step")),
            s.declare_subscriber(k.estop, self._on_estop),
            s.declare_queryable(k.spec, self._on_query("spec")),
            s.liveliness().declare_token(k.alive),
        ):
            for t in threads:
                t.start()
            try:
                yield self
            finally:
                self._stop.set()
                for t in threads:
                    t.join(timeout=5.0)
