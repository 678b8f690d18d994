"""Evaluation between updates, in the learner's process (`--eval-between-updates`).

Where `nasa up`'s layout runs no evaluator service, the learner pauses its
updates when the run's env steps reach a multiple of eval_every and plays the
evaluation episodes itself with the weights it is training, as `nasa train`
does; the actors meanwhile run on until the rate limiter holds them. The
episodes, the eval environment's seed and the rule for which step is due are
the evaluator service's (shared/evaluation.py), so eval.csv means the same
either way. No pictures are made here (the evaluator service's media).
"""

from __future__ import annotations

from collections.abc import Callable

from shared import envs, wire
from shared.agents import Agent
from shared.config import EVAL_SEED_OFFSET, TrainConfig
from shared.envs import PixelEnv
from shared.evaluation import draws_restarter, eval_due, evaluate, final_eval_waits, first_done


class BetweenUpdates:
    def __init__(self, config: TrainConfig, agent: Agent, done_step: int | None,
                 draws: dict | None = None) -> None:
        self.config, self.agent = config, agent
        # A resumed run does not evaluate again the steps its eval.csv holds.
        self.done = first_done(config) if done_step is None else done_step
        self.env: PixelEnv | None = None  # made at the first evaluation
        self.restart_draws: Callable[[], None] = lambda: None
        self._draws = draws  # where a resumed run's evaluation draws stood (its checkpoint's)

    def draws(self) -> dict | None:
        """The evaluation environment's draws now, for the learner's checkpoint (None: none made)."""
        return None if self.env is None else self.env.rng_state()

    def due(self, env_steps: int, final: bool = False) -> int | None:
        """The eval step to play now, or None; the budget's waits for the run's last update
        (`final`: the learner has stopped updating)."""
        if self.done < 0 and self.agent.num_updates == 0:
            return 0  # the untrained policy is step 0's, however far the actors got meanwhile
        target = eval_due(env_steps, self.config, self.done)
        if target is not None and final_eval_waits(target, self.config, self.agent.num_updates, final):
            return None
        return target

    def run(self, target: int) -> wire.EvalResult:
        """The evaluation of step `target`, with the agent's weights of now. envs.EnvFault: an
        episode failed (step `target` is done all the same: the same weights would fail again)."""
        c = self.config
        if self.env is None:
            self.env = envs.from_config(c.env, c.seed + EVAL_SEED_OFFSET)
            self.restart_draws = draws_restarter(self.env, c.eval_same_episodes)
            if self._draws:  # go on from the checkpoint's, as an uninterrupted run would
                self.env.set_rng_state(self._draws)
        self.restart_draws()
        self.done = target
        returns = evaluate(self.agent, self.env, c.eval_episodes)
        return wire.EvalResult(target, self.agent.num_updates, [float(r) for r in returns])
