"""The single-process trainer: one environment, the replay and the agent in one loop.

It is the reference runner, built from the same parts as the services: the
environment loop hands transitions to the replay store (`StoreAdder`), the
intrinsic scorer scores each new transition as the learner does, batches come
through the in-process replay client (`LocalReplay`), and the recorder writes
the same rows and checkpoint core as the learner.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from shared import checkpoint, envs, run_config
from shared.agents import Agent, batch_to_device, collect_action, make_updating_agent
from shared.config import EVAL_SEED_OFFSET, ConfigError, TrainConfig, validate
from shared.device import resolve_device
from shared.env_loop import EnvLoop
from shared.evaluation import draws_restarter, evaluate, is_eval_step
from shared.recorder import Counters, MetricMeans, Recorder
from shared.replay.adder import StoreAdder
from shared.replay.client import LocalReplay
from shared.replay.store import SNAPSHOT_EVERY, open_store
from shared.runlog import checkpointed_step
from shared.scalars import TENSORBOARD_DIR, Scalars
from shared.schedule import step_updates, updates_due
from shared.scoring import IntrinsicScorer, collect_scoring

CHECKPOINT_FILE = "checkpoint.pt"
MAX_FAULTS_IN_A_ROW = 5
"""Episodes abandoned to an EnvFault with none finished between: the run stops rather than reset
forever (a policy that acts NaN faults at every step)."""


class EnvFaultsInARow(RuntimeError):
    """The environment faulted in MAX_FAULTS_IN_A_ROW episodes in a row."""


class Trainer:
    def __init__(self, config: TrainConfig, out: str | Path, state: dict | None = None) -> None:
        c = self.config = validate(config)
        self.out = Path(out)
        self.device = resolve_device(c.device)
        torch.manual_seed(c.seed)  # before any network is built
        self.env = envs.from_config(c.env, c.seed)
        self.eval_env = envs.from_config(c.env, c.seed + EVAL_SEED_OFFSET)
        # Where the evaluation draws stood when the run began, not at the checkpoint resumed from.
        self.restart_eval_draws = draws_restarter(self.eval_env, c.eval_same_episodes)
        if state is not None:  # before any file is opened: a state refused leaves the run as it was
            self._restore_envs(state)
        self.run_config = run_config.RunConfig(c, self.env.spec)
        spec = self.env.spec
        self.agent: Agent = make_updating_agent(c, spec, self.device)
        self.rng = np.random.default_rng(c.seed)
        self.recorder = Recorder(self.out, c.eval_episodes)
        self.scalars = Scalars(self.out / TENSORBOARD_DIR / "train")  # the learner's tags too
        self.store = open_store(self.run_config, self.out / "replay")
        self.replay = LocalReplay(self.store, self.rng, replace=not c.sample_without_replacement)
        self.loop = EnvLoop(self.env, StoreAdder(self.store), c.env.time_limit)
        self.scorer = (IntrinsicScorer(self.agent, self.replay, c.warmup_steps, c.batch_size)
                       if collect_scoring(self.agent, c) else None)
        self.counters = Counters()
        self.means = MetricMeans()
        self.last_checkpoint_step = 0
        self.faults_in_a_row = 0  # 0 at every checkpoint (they are taken at episode ends)
        self.snapshot_every = SNAPSHOT_EVERY
        self.snapshot_error = ""  # the last failed compaction's error, once said

    # -- run folder -------------------------------------------------------------

    @classmethod
    def create(cls, config: TrainConfig, out: str | Path) -> Trainer:
        out = Path(out)
        if (out / CHECKPOINT_FILE).exists() or (out / run_config.CONFIG_FILE).exists():
            raise FileExistsError(f"{out} already holds a run; continue it with --resume {out}")
        trainer = cls(config, out)
        run_config.write_folder(out, trainer.run_config)
        return trainer

    @classmethod
    def resume(cls, out: str | Path, steps: int | None = None, cuda_graph: bool | None = None) -> Trainer:
        """Continue the run in `out` exactly from its last checkpoint (optionally to a new step total,
        or with its updates replayed as CUDA graphs or not)."""
        out = Path(out)
        body = run_config.read_folder(out)
        if body is None:
            raise FileNotFoundError(f"{out} holds no run ({run_config.CONFIG_FILE} is missing)")
        config = run_config.config_from_dict({k: v for k, v in body.items() if k != "spec"})
        # Read the checkpoint before touching the folder: one this version cannot
        # continue is refused with the run left as it was.
        state = None
        if (out / CHECKPOINT_FILE).exists():
            state = checkpoint.load(out / CHECKPOINT_FILE, resolve_device(config.device))
        elif (saved := checkpointed_step(out, config.checkpoint_every)) is not None:
            # Taken for a run killed before its first checkpoint, it would start over and clear
            # the rows it holds.
            raise checkpoint.CheckpointError(
                f"{out} has no {CHECKPOINT_FILE}, though its train.csv goes on past the one saved at "
                f"step {saved}: resumed, the run would start over and erase its eval.csv and "
                f"train.csv. Put its {CHECKPOINT_FILE} back, or start the run again in another folder")
        if steps is not None:
            held = int(state["env_steps"]) if state is not None else 0
            if steps <= held:
                # Nothing would run, and the rows written after the checkpoint would be dropped.
                raise ConfigError(f"--steps {steps}: the run's checkpoint already holds step {held}; "
                                  "give a larger total")
            config.steps = steps
        changed = steps is not None
        if cuda_graph is not None and cuda_graph != config.agent.cuda_graph:
            config.agent.cuda_graph, changed = cuda_graph, True
        trainer = cls(config, out, state)
        if state is not None:
            trainer._restore(state)
        else:  # stopped before its first checkpoint (or a budget that ended first): start over
            # Said, as the rows of eval.csv and train.csv go: a user who asked to continue a
            # finished run expects them kept.
            print(f"nasa train: {out} has no {CHECKPOINT_FILE} (one is written at the first episode end "
                  f"at or past step {config.checkpoint_every}): the run starts over from step 0",
                  flush=True)
            trainer.store.truncate(0)
            trainer.recorder.clear()
            trainer.scalars.purge_step = 0  # and hide the events of the attempt before
        if changed:
            run_config.write_folder(out, trainer.run_config)
        return trainer

    def save_checkpoint(self) -> None:
        # A Ctrl-C here waits for the checkpoint, so the message it prints names the one on disk.
        with checkpoint.stop_signals_deferred():
            self.store.flush()
            self.recorder.checkpoint(
                self.out / CHECKPOINT_FILE, self.agent, self.rng, self.counters,
                env_rng=self.env.rng_state(), eval_env_rng=self.eval_env.rng_state(),
                replay_inserted=self.store.num_inserted,
            )
            self.last_checkpoint_step = self.counters.env_steps
        self.compact_replay()

    def compact_replay(self) -> None:
        """Compact the replay's log now and then, at a checkpoint: its snapshot then holds the very
        rows a resume starts from, and a resume reads it instead of the whole run's log. It is
        written in the background; one that fails (a full disk) loses nothing, the log stays."""
        if (err := self.store.snapshot_error) and err != self.snapshot_error:
            tqdm.write(f"nasa train: compacting the replay log failed, the log is kept: {err}")
        self.snapshot_error = err
        self.store.snapshot_if_due(self.snapshot_every)

    def _restore(self, state: dict) -> None:
        """The rest of a checkpoint's state; the environments' came back at construction."""
        self.counters = self.recorder.restore(state, self.agent, self.rng, truncate=True)
        self.scalars.purge_step = self.counters.env_steps  # the steps after the checkpoint are run again
        self.last_checkpoint_step = self.counters.env_steps
        inserted = int(state["replay_inserted"])
        self.store.truncate(inserted)
        held = min(inserted, self.store.capacity)
        if (size := len(self.store)) < held:
            # Rows the replay evicted after the checkpoint (its capacity is below the run's steps)
            # do not come back: the run goes on from a smaller replay, not exactly as it would have.
            print(f"nasa train: the replay holds {size} of the {held} rows it held at the checkpoint "
                  f"(capacity {self.store.capacity}, evicted since): the resumed run does not continue "
                  "exactly as an uninterrupted one would", flush=True)

    def _restore_envs(self, state: dict) -> None:
        for env, key in ((self.env, "env_rng"), (self.eval_env, "eval_env_rng")):
            try:
                env.set_rng_state(state[key])
            except (KeyError, TypeError, ValueError, IndexError) as err:
                raise checkpoint.CheckpointError(
                    f"{self.out / CHECKPOINT_FILE}: its {key} does not fit task "
                    f"{self.config.env.task}: {err!r}"
                ) from err

    # -- the loop -----------------------------------------------------------------

    def run(self) -> None:
        c, n = self.config, self.counters
        if n.env_steps == 0 and self.recorder.eval_log.rows() == 0 and c.eval_at_start:
            self.run_evaluation()
        progress = tqdm(total=c.steps, initial=n.env_steps, unit="step", dynamic_ncols=True, mininterval=1.0)
        ts = self.loop.reset()
        started, wall0, episode_started = time.monotonic(), n.wall_s, time.monotonic()
        while n.env_steps < c.steps:
            warming_up = n.env_steps < c.warmup_steps
            action = collect_action(self.agent, ts.obs, warming_up, self.rng, self.env.spec.action_dim)
            version = self.agent.num_updates  # the policy that chose the action
            if c.updates_before_store:
                # Counted up to the schedule's, not by the step: a step the environment faults is
                # taken again, and its updates are made once.
                self.update(updates_due(n.env_steps + 1, c) - self.agent.num_updates)
            try:
                ts = self.loop.step(action, version)
            except envs.EnvFault as err:
                # The step did not happen: no transition, no step counted. A reset starts a sound
                # episode, as the actor does; the same steps fault again on a resume, and are
                # handled the same way, so the run still continues exactly.
                self.abandon_episode(err)
                ts, episode_started = self.loop.reset(), time.monotonic()
                continue
            n.env_steps += 1
            if self.scorer is not None:
                self.scorer.score_new()
            if not c.updates_before_store:
                self.update(step_updates(n.env_steps, c))
            n.wall_s = wall0 + time.monotonic() - started
            if is_eval_step(n.env_steps, c):
                self.run_evaluation()
            progress.update(1)
            if ts.last:
                self.faults_in_a_row = 0
                self.end_episode(progress, time.monotonic() - episode_started)
                ts, episode_started = self.loop.reset(), time.monotonic()
        progress.close()
        self.close()

    def close(self) -> None:
        """Release the environments' renderers and the run's files: at the end of a run, or when
        it is stopped (the replay's log is safe however it stops; a resume starts from the last
        checkpoint)."""
        failed: list[OSError] = []
        for close in (self.env.close, self.eval_env.close, self.store.close, self.scalars.close):
            try:  # each, even when one fails (a full disk refuses a flush): the others still close
                close()
            except OSError as err:
                failed.append(err)
        if failed:
            raise failed[0]

    def update(self, count: int) -> None:
        """`count` updates on batches from the replay."""
        for _ in range(count):
            batch = self.replay.sample(self.config.batch_size, wait_s=0.0)
            if self.scorer is not None:  # a no-op while score_new keeps up, as it does in process
                self.scorer.score_batch(batch)
            self.means.add(self.agent.update(batch_to_device(batch, self.device)))

    def abandon_episode(self, err: envs.EnvFault) -> None:
        """The episode under way cannot go on: it gets no train.csv row, and its update means are
        dropped so that the next row describes its own episode. EnvFaultsInARow after too many."""
        self.faults_in_a_row += 1
        self.means.take()
        if self.scorer is not None:
            self.scorer.take_episode_means()
        where = f"step {self.counters.env_steps}, episode step {self.loop.episode_length}"
        if self.faults_in_a_row >= MAX_FAULTS_IN_A_ROW:
            raise EnvFaultsInARow(
                f"the environment faulted in {self.faults_in_a_row} episodes in a row (the last at "
                f"{where}: {err}); a resume would play the same steps, so it would fault again")
        tqdm.write(f"nasa train: episode abandoned at {where}: {err}")

    def end_episode(self, progress: tqdm, elapsed_s: float) -> None:
        c, n, loop = self.config, self.counters, self.loop
        n.episodes += 1
        means = self.means.take() | (self.scorer.take_episode_means() if self.scorer else {})
        row = self.recorder.train_row(n.env_steps, n.episodes, loop.episode_return, loop.episode_length,
                                      self.agent.num_updates, n.wall_s, means,
                                      steps_per_s=loop.episode_length / max(elapsed_s, 1e-9))
        self.scalars.episode(row)
        progress.set_postfix(ret=f"{loop.episode_return:.1f}", refresh=False)
        if n.env_steps - self.last_checkpoint_step >= c.checkpoint_every or n.env_steps >= c.steps:
            self.save_checkpoint()

    def run_evaluation(self) -> None:
        self.restart_eval_draws()
        try:
            returns = evaluate(self.agent, self.eval_env, self.config.eval_episodes)
        except envs.EnvFault as err:  # as the evaluator and the learner: no row for this step
            tqdm.write(f"eval step {self.counters.env_steps}: evaluation failed, no result for this "
                       f"step: {err}")
            return
        row = self.recorder.eval_row(self.counters.env_steps, returns, updates=self.agent.num_updates)
        self.scalars.eval(self.counters.env_steps, row["mean"], row["std"])
        tqdm.write(f"eval step {self.counters.env_steps}: mean return {row['mean']:.1f} +- {row['std']:.1f}")

