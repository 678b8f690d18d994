"""The single-process trainer: one env, the replay store and the agent in one loop.

It is the reference runner: the distributed services are assembled from the
same parts (env, agent, replay store, run log) and measured against it.
"""

from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from shared import checkpoint, envs
from shared.agents import Agent, batch_to_device, collect_action, make_agent
from shared.config import TrainConfig, from_dict, to_dict, validate
from shared.device import resolve_device
from shared.evaluation import evaluate
from shared.replay.store import ReplayStore
from shared.runlog import TRAIN_FIELDS, CsvLog, eval_fields

CHECKPOINT_FILE = "checkpoint.pt"


class Trainer:
    def __init__(self, config: TrainConfig, out: str | Path) -> None:
        self.config = validate(config)
        self.out = Path(out)
        self.device = resolve_device(config.device)
        torch.manual_seed(config.seed)  # before any network is built
        self.env = envs.from_config(config.env, config.seed)
        self.eval_env = envs.from_config(config.env, config.seed + 1_000_000)
        self.agent: Agent = make_agent(
            config.algo, self.env.obs_shape, self.env.action_dim, config.agent, self.device
        )
        self.rng = np.random.default_rng(config.seed)
        self.out.mkdir(parents=True, exist_ok=True)
        self.replay = ReplayStore(
            capacity=config.replay_capacity,
            frame_shape=(3, config.env.image_size, config.env.image_size),
            frame_stack=config.env.frame_stack,
            action_dim=self.env.action_dim,
            data_dir=self.out / "replay",
            compression=config.replay_compression,
        )
        self.eval_log = CsvLog(self.out / "eval.csv", eval_fields(config.eval_episodes))
        self.train_log = CsvLog(self.out / "train.csv", TRAIN_FIELDS)
        self.step = 0
        self.episode = 0
        self.last_checkpoint_step = 0
        self.wall_s = 0.0

    # -- run folder -------------------------------------------------------------

    @classmethod
    def create(cls, config: TrainConfig, out: str | Path) -> Trainer:
        out = Path(out)
        if (out / CHECKPOINT_FILE).exists() or (out / "config.json").exists():
            raise FileExistsError(f"{out} already holds a run; continue it with --resume {out}")
        trainer = cls(config, out)
        (out / "config.json").write_text(json.dumps(to_dict(trainer.config), indent=2) + "\n")
        return trainer

    @classmethod
    def resume(cls, out: str | Path, steps: int | None = None) -> Trainer:
        """Continue the run in `out` exactly from its last checkpoint (optionally to a new step total)."""
        out = Path(out)
        config = from_dict(json.loads((out / "config.json").read_text()))
        # Read the checkpoint before touching the folder: one this version cannot
        # continue is refused with the run left as it was.
        state = None
        if (out / CHECKPOINT_FILE).exists():
            state = checkpoint.load(out / CHECKPOINT_FILE, resolve_device(config.device))
        if steps is not None:
            config.steps = steps
            (out / "config.json").write_text(json.dumps(to_dict(config), indent=2) + "\n")
        trainer = cls(config, out)
        if state is not None:
            trainer.restore(state)
        else:  # killed before its first checkpoint: start over
            trainer.replay.truncate(0)
            trainer.eval_log.truncate(0)
            trainer.train_log.truncate(0)
        return trainer

    def save_checkpoint(self) -> None:
        self.replay.flush()
        checkpoint.save(
            self.out / CHECKPOINT_FILE,
            {
                "agent": self.agent.state_dict(),
                "rng": checkpoint.rng_state(self.rng),
                "env_rng": self.env.rng_state(),
                "eval_env_rng": self.eval_env.rng_state(),
                "step": self.step,
                "episode": self.episode,
                "wall_s": self.wall_s,
                "replay_inserted": self.replay.num_inserted,
                "eval_rows": self.eval_log.rows(),
                "train_rows": self.train_log.rows(),
            },
        )
        self.last_checkpoint_step = self.step

    def restore(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        checkpoint.restore_rng_state(self.rng, state["rng"])
        self.env.set_rng_state(state["env_rng"])
        self.eval_env.set_rng_state(state["eval_env_rng"])
        self.step = self.last_checkpoint_step = int(state["step"])
        self.episode = int(state["episode"])
        self.wall_s = float(state["wall_s"])
        self.replay.truncate(int(state["replay_inserted"]))
        self.eval_log.truncate(int(state["eval_rows"]))
        self.train_log.truncate(int(state["train_rows"]))

    # -- the loop -----------------------------------------------------------------

    def run(self) -> None:
        c = self.config
        agent, env = self.agent, self.env
        if self.step == 0 and self.eval_log.rows() == 0:
            self.run_evaluation()
        progress = tqdm(total=c.steps, initial=self.step, unit="step", dynamic_ncols=True, mininterval=1.0)
        ts = env.reset()
        episode_id = self.replay.begin_episode(ts.frame)
        episode = EpisodeStats()
        started = time.monotonic()
        wall_at_start = self.wall_s
        while self.step < c.steps:
            action = collect_action(agent, ts.obs, self.step < c.warmup_steps, self.rng, env.action_dim)
            next_ts = env.step(action)
            self.step += 1
            bonus = self.score_transition(ts.obs, action, next_ts.obs, episode)
            self.replay.add(
                episode_id,
                action,
                next_ts.reward,
                envs.stored_discount(next_ts, c.env.time_limit),
                next_ts.frame,
                next_ts.last,
                policy_version=agent.num_updates,
                intrinsic=bonus,
            )
            episode.add_reward(next_ts.reward)
            if self.step > c.warmup_steps:
                for _ in range(c.updates_per_step):
                    batch = batch_to_device(self.replay.sample(c.batch_size, self.rng), self.device)
                    episode.add_metrics(agent.update(batch))
            self.wall_s = wall_at_start + time.monotonic() - started
            if self.step % c.eval_every == 0:
                self.run_evaluation()
            ts = next_ts
            progress.update(1)
            if ts.last:
                self.episode += 1
                self.train_log.append(episode.row(self.step, self.episode, agent, self.wall_s))
                progress.set_postfix(ret=f"{episode.total:.1f}", refresh=False)
                if self.step - self.last_checkpoint_step >= c.checkpoint_every or self.step >= c.steps:
                    self.save_checkpoint()
                ts = env.reset()
                episode_id = self.replay.begin_episode(ts.frame)
                episode = EpisodeStats()
        progress.close()
        self.replay.close()

    def score_transition(
        self, obs: np.ndarray, action: np.ndarray, next_obs: np.ndarray, episode: EpisodeStats
    ) -> float:
        """The intrinsic reward stored with a transition (`collect` timing, as the paper).

        During warm-up the reference stores none (0); `fresh` timing and agents
        without intrinsic rewards leave the slot unscored (NaN).
        """
        c = self.config
        if not self.agent.uses_intrinsic or c.agent.intrinsic_timing != "collect":
            return math.nan
        if self.step <= c.warmup_steps:
            return 0.0
        d = self.device
        scores = self.agent.score(
            torch.as_tensor(obs, device=d)[None],
            torch.as_tensor(action, device=d)[None],
            torch.as_tensor(next_obs, device=d)[None],
        )
        episode.add_intrinsic(scores["novelty"].item(), scores["surprise"].item())
        return scores["intrinsic"].item()

    def run_evaluation(self) -> None:
        returns = evaluate(self.agent, self.eval_env, self.config.eval_episodes)
        row = {"step": self.step, "mean": float(np.mean(returns)), "std": float(np.std(returns))}
        row |= {f"return_{i}": r for i, r in enumerate(returns)}
        self.eval_log.append(row)
        tqdm.write(f"eval step {self.step}: mean return {row['mean']:.1f} +- {row['std']:.1f}")


class EpisodeStats:
    """Running sums for one train.csv row."""

    def __init__(self) -> None:
        self.total = 0.0
        self.length = 0
        self.sums: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self.started = time.monotonic()

    def add_reward(self, reward: float) -> None:
        self.total += reward
        self.length += 1

    def add_intrinsic(self, novelty: float, surprise: float) -> None:
        self.add_metrics({"novelty_mean": novelty, "surprise_mean": surprise})

    def add_metrics(self, metrics: dict[str, float]) -> None:
        for key, value in metrics.items():
            self.sums[key] += value
            self.counts[key] += 1

    def row(self, step: int, episode: int, agent: Agent, wall_s: float) -> dict:
        means = {k: self.sums[k] / self.counts[k] for k in self.sums if k in TRAIN_FIELDS}
        elapsed = max(time.monotonic() - self.started, 1e-9)
        return {
            "step": step,
            "episode": episode,
            "return": self.total,
            "length": self.length,
            "updates": agent.num_updates,
            "steps_per_s": self.length / elapsed,
            "wall_s": wall_s,
            **means,
        }
