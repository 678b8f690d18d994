"""The learner without its messaging: agent, scorer, records, checkpoint and status.

`LearnerCore` is what the learner service wraps in Zenoh plumbing: it trains
on a batch (scoring its unscored rows first), records evaluations and
finished episodes, checkpoints, and builds /status. It talks to the replay
only through a `ReplayClient`, so unit tests drive it with the in-process
`LocalReplay` and no Zenoh.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from services.learner.status import StatusBoard
from shared import checkpoint, wire
from shared.agents import batch_to_device, make_updating_agent
from shared.agents.base import nonfinite_skips
from shared.evaluation import final_eval_waits, is_eval_step, newest_eval_step
from shared.recorder import Counters, MetricMeans, Recorder
from shared.replay.client import Batch, ReplayClient
from shared.run_config import RunConfig
from shared.scalars import TENSORBOARD_DIR, Scalars
from shared.schedule import burst_extra, total_updates
from shared.scoring import IntrinsicScorer, collect_scoring
from shared.service import Log

CHECKPOINT = "learner/checkpoint.pt"
CHECKPOINT_RETRY_S = 30.0


class LearnerCore:
    def __init__(self, run: RunConfig, out: Path, client: ReplayClient, device: torch.device) -> None:
        c = self.config = run.config
        self.run, self.device, self.out = run, device, Path(out)
        spec = run.spec
        # Seeded before any network is built, as `nasa train` does: a seed's initial weights are
        # the same in both runners and from one launch to the next.
        torch.manual_seed(c.seed)
        self.agent = make_updating_agent(c, spec, device)
        self.rng = np.random.default_rng(c.seed)
        self.recorder = Recorder(self.out, c.eval_episodes)
        self.scorer = (IntrinsicScorer(self.agent, client, c.warmup_steps, c.batch_size)
                       if collect_scoring(self.agent, c) else None)
        self.board = StatusBoard()
        self.log = Log("learner")
        self.checkpoint_error = ""  # why the last checkpoint was not written ("" if it was)
        self._checkpoint_retry_at = 0.0
        self.scalars = Scalars(self.out / TENSORBOARD_DIR / "learner")
        self._eval_sent: int | None = None  # the eval step whose weights went to the evaluator
        self.counters = Counters()
        self.means = MetricMeans()
        self.policy_version = 0
        self.target_updates = total_updates(c)
        self.last_checkpoint_step = 0
        self.resumed = False
        self.eval = self.recorder.last_eval() or {"step": None, "mean": None, "std": None}
        self.last_scoring_s = 0.0  # the last train_on's time in scoring owed rows
        self._skips_seen = 0  # the agent's skipped optimizer steps after the last update
        # Orders weights across learner restarts; past the checkpoint's, should this host's clock
        # be behind the one the run's last learner ran on (actors keep the newest epoch's weights).
        self.epoch = wire.restart_stamp(1000, 62)
        # Evaluations between updates: their environment's draws, into and out of the checkpoint.
        self.eval_draws: Callable[[], dict | None] = lambda: None
        self.restored_eval_draws: dict | None = None
        if (self.out / CHECKPOINT).exists():
            self.restore(checkpoint.load(self.out / CHECKPOINT, device))

    # -- training -----------------------------------------------------------------

    def train_on(self, batch: Batch, on_device: dict[str, torch.Tensor] | None = None) -> dict[str, float]:
        """One update: score what the collect timing still owes, then update on the batch.
        `on_device`: the batch already on the device (shared.prefetch); its intrinsic rewards are
        the host batch's once scored, so only that column is copied again.

        A batch with a non-finite value is dropped (no update; its rows' indices logged); an
        update whose loss or gradient is non-finite skips that optimizer step (optimizer_step)
        and is counted as skipped. Either way no NaN reaches the weights."""
        if self.scorer is not None:
            began = time.perf_counter()
            self.scorer.score_new()
            self.scorer.score_batch(batch)
            self.last_scoring_s = time.perf_counter() - began
        bad = nonfinite_rows(batch, intrinsic=self.scorer is not None)
        if len(bad):
            index = batch["index"][bad].tolist()
            n = self.board.count_nonfinite_batch(index)
            self.log.every("nonfinite-batch", 5.0, f"dropped batch {n}: non-finite values in rows "
                           f"{index[:16]}")
            return {}
        self.board.record_lag(self.agent.num_updates, batch["policy_version"])
        if on_device is None:
            on_device = batch_to_device(batch, self.device)
        else:
            on_device["intrinsic"] = torch.from_numpy(batch["intrinsic"]).to(self.device)
        metrics = self.agent.update(on_device)
        skipped, self._skips_seen = self._skips_seen, nonfinite_skips(self.agent)  # one read per update
        if self._skips_seen > skipped or not all(np.isfinite(v) for v in metrics.values()):
            n = self.board.count_skipped_update()
            self.log.every("nonfinite-update", 5.0, f"skipped update ({n} so far): non-finite loss or "
                           f"gradient {metrics}")
        self.board.record_update(metrics)
        self.means.add({k: v for k, v in metrics.items() if np.isfinite(v)})
        return metrics

    def weights_message(self, epoch: int, evaluation: bool = False) -> bytes | None:
        """The policy's weights as published; version = the update count. None (nothing to
        publish) if a tensor is not finite. `evaluation`: the evaluator's weights of this eval
        period, with the autoencoder's modules the policy lacks (`view_extras`: the decoder, and SAC-AE's
        critic encoder) so it can show the autoencoder's view."""
        state = self.agent.policy_state_dict()
        if not all_finite(state):
            self.log.every("nonfinite-weights", 5.0, "weights not published: a tensor is not finite")
            return None
        self.policy_version = self.agent.num_updates
        if evaluation:
            self._eval_sent = self.eval_step()
            state |= self.agent.view_state_dict()
        tensors = wire.pack_tensors(state)
        return wire.encode(wire.Weights(epoch, self.policy_version, self.env_steps, tensors))

    def eval_step(self) -> int:
        """The newest eval step reached, the budget's own too where it is no multiple of eval_every."""
        return newest_eval_step(self.env_steps, self.config)

    def eval_weights_due(self, final: bool = False) -> bool:
        """Whether an eval step was reached since the evaluator's weights last went out: it plays
        each evaluation with the weights of its step, as `nasa train` does, and takes in only those.
        The budget's step waits for the run's last update (`final`: the learner has stopped updating)."""
        step = self.eval_step()
        if final_eval_waits(step, self.config, self.agent.num_updates, final):
            return False
        return step != self._eval_sent

    def done(self) -> bool:
        return self.board.replay["done"] and self.agent.num_updates >= self.target_updates

    @property
    def env_steps(self) -> int:
        return max(self.board.env_steps, self.counters.env_steps)

    # -- records --------------------------------------------------------------------

    def eval_problem(self, r: wire.EvalResult) -> str | None:
        """Why an evaluation result cannot be this run's (None: it can). One recorded at a step
        the run never evaluates would hold back every real one after it."""
        c = self.config
        if not is_eval_step(r.step, c):
            return f"step {r.step} is not an evaluation step of this run (every {c.eval_every} to {c.steps})"
        if len(r.returns) != c.eval_episodes:
            return f"{len(r.returns)} returns, the run evaluates {c.eval_episodes} episodes"
        return None

    def record_eval(self, r: wire.EvalResult) -> dict | None:
        """An evaluation's row in eval.csv; None if that step is recorded already (sent again)."""
        if self.eval["step"] is not None and r.step <= self.eval["step"]:
            return None
        row = self.recorder.eval_row(r.step, r.returns, updates=r.policy_version)
        self.eval = {"step": r.step, "mean": row["mean"], "std": row["std"]}
        self.scalars.eval(r.step, row["mean"], row["std"])
        return row

    def record_episode(self, episode_return: float, length: int, wall_s: float) -> None:
        """A training episode an actor finished: one train.csv row with the updates' means since the last."""
        self.counters.episodes += 1
        means = self.means.take() | (self.scorer.take_episode_means() if self.scorer else {})
        env_rate = self.board.rates()[0]  # the fleet's, as nasa train's one actor is its whole fleet
        row = self.recorder.train_row(self.env_steps, self.counters.episodes, episode_return, length,
                                      self.agent.num_updates, wall_s, means,
                                      steps_per_s=env_rate if env_rate > 0 else None)
        self.scalars.episode(row)

    # -- checkpoint -----------------------------------------------------------------

    def checkpoint_due(self) -> bool:
        if time.monotonic() < self._checkpoint_retry_at:
            return False
        every = self.config.checkpoint_every
        return self.env_steps // every > self.last_checkpoint_step // every

    def save_checkpoint(self, wall_s: float) -> bool:
        """Checkpoint if every tensor of the agent is finite and the write succeeds; else the last
        checkpoint stays as it was (written to a temporary file, then renamed) and the next try
        comes CHECKPOINT_RETRY_S later (False)."""
        self.checkpoint_error = ""
        if not all_finite(self.agent.state_dict()):
            self.checkpoint_error = "a tensor is not finite"
        else:
            counters = dataclasses.replace(self.counters, env_steps=self.env_steps, wall_s=wall_s)
            try:
                self.recorder.checkpoint(self.out / CHECKPOINT, self.agent, self.rng, counters,
                                         policy_version=self.policy_version, epoch=self.epoch,
                                         eval_env_rng=self.eval_draws(),
                                         intrinsic=self.scorer.state() if self.scorer else None)
            except (OSError, RuntimeError) as err:  # a full disk (torch.save raises RuntimeError): retry
                self.checkpoint_error = f"{type(err).__name__}: {err}"
                self.board.writes.failed("checkpoint", err)
            else:
                self.board.writes.ok("checkpoint")
                self.counters = counters
                self.last_checkpoint_step = counters.env_steps
                return True
        self._checkpoint_retry_at = time.monotonic() + CHECKPOINT_RETRY_S
        self.log.every("checkpoint", 5.0, f"checkpoint not written: {self.checkpoint_error}")
        return False

    def restore(self, state: dict) -> None:
        self.counters = self.recorder.restore(state, self.agent, self.rng, truncate=False)
        # train.csv keeps the episodes that ended after the checkpoint (they happened): number on
        # from the last of them, and let the clock not run back.
        if (last := self.recorder.last_episode()) is not None:
            self.counters.episodes = max(self.counters.episodes, last[0])
            self.counters.wall_s = max(self.counters.wall_s, last[1])
        self.policy_version = int(state["policy_version"])
        self.epoch = max(self.epoch, int(state.get("epoch", -1)) + 1)
        self.restored_eval_draws = state.get("eval_env_rng")
        if self.scorer is not None and isinstance(scores := state.get("intrinsic"), dict):
            self.scorer.load_state(scores)  # an older checkpoint has none: they start again here
        self.last_checkpoint_step = self.counters.env_steps
        self.board.seen_env_steps(self.counters.env_steps)
        self.resumed = True

    # -- status ---------------------------------------------------------------------

    def status(self, run_id: str, wall_s: float) -> dict:
        c = self.config
        fleet = self.board.snapshot()
        updates = self.agent.num_updates
        learning_steps = fleet["env_steps"] - c.warmup_steps
        # The burst's updates beyond G are no step's, so the ratio shows G when it holds.
        paced = max(0, updates - burst_extra(c)) if learning_steps > 0 else 0
        return {
            "run_id": run_id,
            "algo": c.algo,
            "task": c.env.task,
            "device": str(self.device),
            "config_digest": self.run.digest(),
            "steps_budget": c.steps,
            "action_repeat": c.env.action_repeat,
            "warmup_steps": c.warmup_steps,
            "updates": updates,
            "updates_target_per_env_step": c.updates_per_step,
            "updates_per_env_step": paced / learning_steps if learning_steps > 0 else 0.0,
            "policy_version": self.policy_version,
            "eval": dict(self.eval),
            "intrinsic": self.scorer.status() if self.scorer else
            {"novelty_mean": None, "surprise_mean": None, "scored": 0, "scored_at_first_sample": 0,
             "zeroed": 0},
            "resumed": self.resumed,
            "wall_s": round(wall_s, 3),
            **fleet,
        }


def nonfinite_rows(batch: Batch, intrinsic: bool) -> np.ndarray:
    """Rows of a batch with a non-finite action, reward or discount (and intrinsic reward, when
    the agent uses it: unscored NaN rows are the scorer's to fill before this check)."""
    keys = ("action", "reward", "discount", "intrinsic") if intrinsic else ("action", "reward", "discount")
    bad = np.zeros(len(batch["index"]), bool)
    for key in keys:
        values = batch[key].reshape(len(bad), -1)
        bad |= ~np.isfinite(values).all(axis=1)
    return np.flatnonzero(bad)


def all_finite(state: object) -> bool:
    """Whether every floating tensor in a (nested) state dict is finite (one device sync, two where
    a sum overflows)."""
    tensors = _float_tensors(state)
    if not tensors:
        return True
    # A NaN or an infinity makes its tensor's sum non-finite, so finite sums prove every element
    # finite; summing is several times cheaper than an elementwise test, which the learner does
    # before each publish. A sum can also overflow from finite values: then test element by element.
    sums = torch.stack([t.sum(dtype=torch.float32).to(tensors[0].device) for t in tensors])
    if bool(torch.isfinite(sums).all()):
        return True
    return bool(torch.stack([torch.isfinite(t).all().to(tensors[0].device) for t in tensors]).all())


def _float_tensors(state: object) -> list[torch.Tensor]:
    if isinstance(state, torch.Tensor):
        return [state] if state.is_floating_point() else []
    if isinstance(state, dict):
        state = list(state.values())
    if isinstance(state, list | tuple):
        return [t for v in state for t in _float_tensors(v)]
    return []
