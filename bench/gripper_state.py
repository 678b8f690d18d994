"""How many steps the gripper stand-in takes to learn when pixels are not the problem.

The project's TD3 core (the critic, actor, TD target and update order of every TD3 agent here)
learns `gripper-valve` from the simulator's true state instead of the camera: the valve's and the
target's angles (cos, sin, and of their difference) and the four finger joints' angles and
setpoints. `--without-difference` leaves the difference out: the state then holds what a frame
shows (the valve, the target, the fingers), and the agent must relate the two angles itself, as a
pixel agent must. `--angle-noise DEG` reads both angles with Gaussian noise of that many degrees
at every step, as an encoder that holds them only approximately would. `--valve-friction` and
`--valve-damping` change the stand-in's valve joint (its friction loss in N m, its damping in
N m s), to see how the task's physics sets the steps it takes to learn. Settings are cpu-small's
for the gripper (hidden 256, batch 64, G = 1, warm-up 500, exploration noise 0.1, 20 evaluation
episodes), with the encoder replaced by the state itself.
Every `--eval-every` steps it evaluates on a separate stand-in (seed + 1,000,000).

What to read it against: a policy that ignores the target (the untrained one, or one that turns
the valve at random) scores -25 on average, since the target is uniform: a mean distance of pi/2,
a reward of -1/2 a step over 50 steps. A pixel agent is not expected to learn faster than this
one: where this one needs N steps, a 30-minute pixel run of fewer steps says little about the method.

    python -m bench.gripper_state [--steps 50000] [--eval-every 2500] [--seed 0] [--without-difference]
        [--angle-noise DEG] [--valve-friction NM] [--valve-damping NMS] [--updates-per-step 1]
        [--gamma G] [--actor-lr LR] [--exploration-noise S] [--threads N]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch

from shared.agents import PixelTD3
from shared.agents.base import adam
from shared.config import EVAL_SEED_OFFSET, TrainConfig, default_config
from shared.gripper.sim import EPISODE_STEPS, ValveSim

TASK = "gripper-valve"
STATE_DIM = 14
NOISE_STREAM = 0x6E6F  # keeps the angle noise's draws apart from the stand-in's own
DIFFERENCE = slice(4, 6)  # cos and sin of target - valve, in `StateValve.state()`
IGNORES_TARGET = -EPISODE_STEPS / 2  # a mean distance of pi/2 is a reward of -1/2 a step


class StateValve(ValveSim):
    """The stand-in without its camera: reset and step return `state()` where a frame would be;
    with `difference=False`, without the two elements of the target's angle from the valve; with
    `angle_noise` > 0, both angles read with Gaussian noise of that many degrees (its own draws,
    from the seed, so the stand-in's draws do not change); `valve_friction` and `valve_damping`,
    where given, in place of the model's valve joint's."""

    def __init__(self, task: str, seed: int, *args, difference: bool = True,  # noqa: ANN002 (ValveSim's)
                 angle_noise: float = 0.0, valve_friction: float | None = None,
                 valve_damping: float | None = None, **kwargs) -> None:  # noqa: ANN003
        self.difference = difference
        self.angle_noise = math.radians(angle_noise)
        self._noise = np.random.default_rng([seed, NOISE_STREAM])
        super().__init__(task, seed, *args, **kwargs)
        if valve_friction is not None:
            self.model.dof_frictionloss[self._valve_dof] = valve_friction
        if valve_damping is not None:
            self.model.dof_damping[self._valve_dof] = valve_damping

    @property
    def state_dim(self) -> int:
        return STATE_DIM if self.difference else STATE_DIM - 2

    def render(self) -> np.ndarray:
        return self.state()

    def state(self) -> np.ndarray:
        valve, target = self.valve_angle, self.target_angle
        if self.angle_noise > 0:
            valve, target = np.array([valve, target]) + self._noise.normal(0.0, self.angle_noise, 2)
        fingers = self.data.qpos[self._finger_qpos]
        angles = (math.cos(valve), math.sin(valve), math.cos(target), math.sin(target),
                  math.cos(target - valve), math.sin(target - valve))
        state = np.concatenate([angles, fingers, self._setpoint]).astype(np.float32)
        return state if self.difference else np.delete(state, DIFFERENCE)


def state_agent(seed: int, agent_settings: dict | None = None,
                state_dim: int = STATE_DIM) -> tuple[PixelTD3, TrainConfig]:
    """TD3 with cpu-small's settings (and `agent_settings` over them: AgentConfig fields) whose
    'encoder' passes a state of `state_dim` through; and those settings."""
    torch.manual_seed(seed)
    config = default_config("pixel_td3", "cpu-small", TASK)
    for name, value in (agent_settings or {}).items():
        if not hasattr(config.agent, name):
            raise ValueError(f"unknown agent setting {name!r}")
        setattr(config.agent, name, value)
    config.agent.latent_dim = state_dim
    config.agent.random_shift = 0  # the variant shifts frames; a state has none
    agent = PixelTD3((3, 16, 16), 4, config.agent, torch.device("cpu"))
    agent.encoder = torch.nn.Identity()
    agent.critic_opt = adam(agent.critic.parameters(), config.agent.critic_lr)
    return agent, config


def evaluate(agent: PixelTD3, env: StateValve, episodes: int) -> float:
    """The mean return of `episodes` episodes with the deterministic policy."""
    unused = np.random.default_rng(0)  # explore=False draws nothing
    returns = []
    for _ in range(episodes):
        state, _, _, last = env.reset()
        total = 0.0
        while not last:
            state, reward, _, last = env.step(agent.act(state, explore=False, rng=unused).astype(np.float64))
            total += reward
        returns.append(total)
    return float(np.mean(returns))


def train(steps: int, eval_every: int, seed: int, eval_episodes: int | None = None,
          warmup: int | None = None, agent_settings: dict | None = None, updates_per_step: int = 1,
          difference: bool = True, angle_noise: float = 0.0, valve: dict | None = None) -> dict:
    """Learn from state for `steps` env steps, `updates_per_step` updates (each on its own
    minibatch) after each; the evaluations' means by step. Evaluation episodes and warm-up default
    to cpu-small's gripper settings; `difference`, `angle_noise` and `valve` (`valve_friction`,
    `valve_damping`) as `StateValve`'s."""
    options = {"difference": difference, "angle_noise": angle_noise, **(valve or {})}
    env = StateValve(TASK, seed, **options)
    eval_env = StateValve(TASK, seed + EVAL_SEED_OFFSET, **options)
    agent, config = state_agent(seed, agent_settings, env.state_dim)
    batch_size = config.batch_size
    eval_episodes = config.eval_episodes if eval_episodes is None else eval_episodes
    warmup = config.warmup_steps if warmup is None else warmup
    rng = np.random.default_rng(seed)
    obs = np.zeros((steps, env.state_dim), np.float32)
    next_obs = np.zeros_like(obs)
    actions = np.zeros((steps, 4), np.float32)
    rewards = np.zeros(steps, np.float32)
    evals = {0: evaluate(agent, eval_env, eval_episodes)}
    print(f"step 0: {evals[0]:.1f}", flush=True)
    start = time.perf_counter()
    state = env.reset()[0]
    for i in range(steps):
        action = rng.uniform(-1, 1, 4) if i < warmup else agent.act(state, explore=True, rng=rng)
        next_state, reward, _, last = env.step(action.astype(np.float64))
        obs[i], actions[i], rewards[i], next_obs[i] = state, action, reward, next_state
        state = env.reset()[0] if last else next_state
        for _ in range(updates_per_step if i >= warmup else 0):
            rows = rng.integers(0, i + 1, batch_size)
            agent.update({  # the time limit is not an end: discount 1, as the pixel runs store it
                "obs": torch.from_numpy(obs[rows]), "next_obs": torch.from_numpy(next_obs[rows]),
                "action": torch.from_numpy(actions[rows]), "reward": torch.from_numpy(rewards[rows]),
                "discount": torch.ones(batch_size),
            })
        if (i + 1) % eval_every == 0:
            evals[i + 1] = evaluate(agent, eval_env, eval_episodes)
            print(f"step {i + 1}: {evals[i + 1]:.1f} ({time.perf_counter() - start:.0f} s)", flush=True)
    env.close()
    eval_env.close()
    return {"eval_episodes": eval_episodes, "warmup": warmup,
            "evals": {str(k): round(v, 2) for k, v in evals.items()}, "updates": agent.num_updates,
            "seconds": round(time.perf_counter() - start, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--eval-every", type=int, default=2_500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--without-difference", action="store_true",
                        help="leave the target's angle from the valve out of the state")
    parser.add_argument("--angle-noise", type=float, default=0.0, metavar="DEG",
                        help="read the valve's and the target's angles with Gaussian noise of DEG degrees")
    parser.add_argument("--valve-friction", type=float, metavar="NM",
                        help="the valve joint's friction loss, N m (the model's: 0.01)")
    parser.add_argument("--valve-damping", type=float, metavar="NMS",
                        help="the valve joint's damping, N m s (the model's: 0.005)")
    parser.add_argument("--updates-per-step", type=int, default=1, help="G (cpu-small: 1)")
    parser.add_argument("--gamma", type=float, help="the discount (cpu-small: 0.99)")
    parser.add_argument("--actor-lr", type=float, help="the actor's learning rate (cpu-small: 1e-4)")
    parser.add_argument("--exploration-noise", type=float, help="cpu-small: 0.1")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's); results differ "
                        "in rounding, and so in their path, from one thread count to another")
    args = parser.parse_args()
    if min(args.steps, args.eval_every, args.updates_per_step,
           1 if args.threads is None else args.threads) < 1 or args.seed < 0:
        parser.error("--steps, --eval-every, --updates-per-step and --threads must be >= 1, --seed >= 0")
    if not 0.0 <= args.angle_noise <= 360.0:  # also refuses nan
        parser.error("--angle-noise must be between 0 and 360 degrees")
    valve = {name: value for name in ("valve_friction", "valve_damping")
             if (value := getattr(args, name)) is not None}
    if not all(0.0 <= value < math.inf for value in valve.values()):  # also refuses nan
        parser.error("--valve-friction and --valve-damping must be finite and >= 0")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    settings = {name: value for name in ("gamma", "actor_lr", "exploration_noise")
                if (value := getattr(args, name)) is not None}
    result = {"task": TASK, "observation": "state", "steps": args.steps, "seed": args.seed,
              "ignores_target": IGNORES_TARGET, "updates_per_step": args.updates_per_step,
              "difference": not args.without_difference, "angle_noise_deg": args.angle_noise,
              "agent_settings": settings, "valve": valve, "threads": torch.get_num_threads()}
    result |= train(args.steps, args.eval_every, args.seed, agent_settings=settings,
                    updates_per_step=args.updates_per_step, difference=not args.without_difference,
                    angle_noise=args.angle_noise, valve=valve)
    evals = list(result["evals"].values())
    result["best"], result["last"] = max(evals), evals[-1]
    print(json.dumps(result))


if __name__ == "__main__":
    main()
