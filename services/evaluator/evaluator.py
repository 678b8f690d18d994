"""The evaluator service: deterministic evaluation episodes with the newest weights.

Each time the global env step count (the replay's stats) reaches a multiple
of config.eval_every, it runs config.eval_episodes deterministic episodes
(shared/evaluation.py, as the single-process trainer) with the newest weights
it holds and publishes the returns (`eval/result`, BLOCK); the learner writes
them to eval.csv. Step 0 is evaluated with the learner's initial weights
(version 0), as the trainer does. If evaluation is slower than training, it
evaluates the newest multiple reached and skips those in between.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import zenoh

from shared import envs, wire
from shared.agents import make_agent
from shared.evaluation import evaluate
from shared.service import Log, StopFlag
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK


@dataclass
class EvaluatorArgs(ServiceArgs):
    """The evaluator: every eval_every global env steps, deterministic episodes with the newest weights."""

    eval_device: str = "cpu"
    threads: int = 1


class EvaluatorService:
    def __init__(self, args: EvaluatorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        c = args.config
        self.args, self.config, self.session, self.stop = args, c, session, stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("evaluator")
        torch.set_num_threads(max(1, args.threads))
        self.env = envs.from_config(c.env, c.seed + 1_000_000)
        self.agent = make_agent(
            c.algo, self.env.obs_shape, self.env.action_dim, c.agent, torch.device(args.eval_device)
        )
        self.policy_version: int | None = None
        self._held: tuple[int, int] | None = None
        self.global_steps: int | None = None
        self.invalid = 0
        self._pending: bytes | None = None

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def _on_weights(self, sample: zenoh.Sample) -> None:
        self._pending = sample.payload.to_bytes()

    def _on_weights_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None and self._pending is None and self.policy_version is None:
            self._pending = reply.ok.payload.to_bytes()

    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            n = wire.decode(sample.payload.to_bytes(), wire.ReplayStats).num_inserted
        except wire.WireError as err:
            return self._invalid(f"replay stats: {err}")
        self.global_steps = max(self.global_steps or 0, n)

    def _on_stop(self, sample: zenoh.Sample) -> None:
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except wire.WireError as err:
            self._invalid(f"stop: {err}")

    def load_weights(self) -> None:
        data, self._pending = self._pending, None
        if data is None:
            return
        try:
            msg = wire.decode(data, wire.Weights)
            if not wire.newer_weights(msg, self._held):
                return
            self.agent.load_policy_state_dict(wire.unpack_tensors(msg.tensors))
        except (wire.WireError, RuntimeError, KeyError) as err:
            return self._invalid(f"weights: {err}")
        self._held = (msg.epoch, msg.version)
        self.policy_version = msg.version
        self.global_steps = max(self.global_steps or 0, msg.env_steps)

    def run(self) -> None:
        s, k, c = self.session, self.keys, self.config
        with (
            s.declare_subscriber(k.weights, self._on_weights),
            s.declare_subscriber(k.replay_stats, self._on_stats),
            s.declare_subscriber(k.stop, self._on_stop),
            s.liveliness().declare_token(k.alive("evaluator", 0)),
        ):
            s.get(k.weights_latest, self._on_weights_reply, timeout=10.0)
            self.log(f"evaluating every {c.eval_every} env steps, {c.eval_episodes} episodes")
            done = -1
            while not self.stop.wait(0.1):
                self.load_weights()
                if self.policy_version is None or self.global_steps is None:
                    continue
                target = (min(self.global_steps, c.steps) // c.eval_every) * c.eval_every
                if target <= done:
                    continue
                returns = evaluate(self.agent, self.env, c.eval_episodes)
                msg = wire.EvalResult(target, self.policy_version, [float(r) for r in returns])
                s.put(k.eval_result, wire.encode(msg), congestion_control=BLOCK)
                self.log(f"step {target} (policy {self.policy_version}): mean {np.mean(returns):.1f}")
                done = target
            self.log(f"stopping ({self.stop.reason})")


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: EvaluatorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        EvaluatorService(args, session, stop).run()

    run_service(EvaluatorArgs, argv, "python -m services.evaluator", run)
