"""dm_control pixel environments: task names, rendering quality and frame stacking.

`make()` composes thin layers the way DrQ-v2's `dmc.py` does: the suite task, a
pixel renderer, action repeat and a frame stack. Every environment the system
steps (simulation, the valve stand-in, the real gripper) exposes this `PixelEnv`
interface, so actors never care which one they hold.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # must be set before dm_control loads a GL backend

from collections import deque  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from typing import TYPE_CHECKING, Literal, Protocol  # noqa: E402

import numpy as np  # noqa: E402

if TYPE_CHECKING:
    from shared.config import EnvConfig

RenderQuality = Literal["paper", "fast"]
PAPER_TASKS = (
    "ball_in_cup-catch",
    "cartpole-balance",
    "reacher-hard",
    "finger-spin",
    "walker-walk",
    "cheetah-run",
)


class UnknownTaskError(ValueError):
    """A task name that is not `domain-task` of the DeepMind Control Suite."""


@dataclass(frozen=True)
class TimeStep:
    """One environment step as seen by an agent.

    `frame` is the newest rendered frame (3, H, W); `obs` is the stack of the
    last `frame_stack` frames along channels. `discount` is the suite's: 1.0 at
    a time-limit ending, 0.0 at a true terminal.
    """

    obs: np.ndarray
    frame: np.ndarray
    reward: float
    discount: float
    first: bool
    last: bool


class PixelEnv(Protocol):
    action_dim: int
    obs_shape: tuple[int, int, int]

    def reset(self) -> TimeStep: ...
    def step(self, action: np.ndarray) -> TimeStep: ...
    def rng_state(self) -> dict: ...
    def set_rng_state(self, state: dict) -> None: ...


def all_tasks() -> list[str]:
    from dm_control import suite

    return sorted(f"{domain}-{task}" for domain, task in suite.ALL_TASKS)


def parse_task(name: str) -> tuple[str, str]:
    """Split `domain-task`, failing with the list of valid names."""
    valid = all_tasks()
    if name not in valid:
        raise UnknownTaskError(
            f"unknown task {name!r}; valid tasks are: {', '.join(valid)}"
        )
    domain, task = name.split("-", 1)
    return domain, task


class DMCPixels:
    """A suite task rendered to (3, H, W) uint8 frames, with action repeat."""

    def __init__(
        self,
        task: str,
        seed: int,
        image_size: int = 84,
        camera_id: int = 0,
        action_repeat: int = 1,
        render_quality: RenderQuality = "paper",
    ) -> None:
        from dm_control import suite

        domain, task_name = parse_task(task)
        if action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        self._env = suite.load(domain, task_name, task_kwargs={"random": seed})
        if render_quality == "fast":
            # Shadows and multisampling are most of the software-GL render cost;
            # the quality struct is read when the GL context is first made.
            quality = self._env.physics.model.vis.quality
            quality.shadowsize = 512
            quality.offsamples = 0
        elif render_quality != "paper":
            raise ValueError(f"render_quality must be 'paper' or 'fast', got {render_quality!r}")
        spec = self._env.action_spec()
        if not (np.all(spec.minimum == -1.0) and np.all(spec.maximum == 1.0)):
            raise ValueError(f"task {task} has actions outside [-1, 1]: {spec}")
        self.action_dim = int(spec.shape[0])
        self.image_size = image_size
        self.camera_id = camera_id
        self.action_repeat = action_repeat

    def render(self) -> np.ndarray:
        pixels = self._env.physics.render(self.image_size, self.image_size, camera_id=self.camera_id)
        return np.ascontiguousarray(pixels.transpose(2, 0, 1))

    def rng_state(self) -> dict:
        """The task's random state, which draws each episode's initial state."""
        name, keys, pos, has_gauss, cached = self._env.task.random.get_state()
        return {"name": name, "keys": keys.tolist(), "pos": pos, "has_gauss": has_gauss, "cached": cached}

    def set_rng_state(self, state: dict) -> None:
        keys = np.asarray(state["keys"], dtype=np.uint32)
        self._env.task.random.set_state(
            (state["name"], keys, state["pos"], state["has_gauss"], state["cached"])
        )

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        self._env.reset()
        return self.render(), 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action shape {action.shape}, expected ({self.action_dim},)")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action has non-finite values: {action}")
        reward, discount = 0.0, 1.0
        for _ in range(self.action_repeat):
            ts = self._env.step(action)
            reward += ts.reward or 0.0
            discount *= ts.discount if ts.discount is not None else 1.0
            if ts.last():
                break
        return self.render(), reward, discount, ts.last()


class FrameStack:
    """Stacks the last k frames along channels; an episode starts with its first frame k times."""

    def __init__(self, env: DMCPixels, k: int = 3) -> None:
        if k < 1:
            raise ValueError(f"frame_stack must be >= 1, got {k}")
        self._env = env
        self._frames: deque[np.ndarray] = deque(maxlen=k)
        self.k = k
        self.action_dim = env.action_dim
        self.obs_shape = (3 * k, env.image_size, env.image_size)

    def rng_state(self) -> dict:
        return self._env.rng_state()

    def set_rng_state(self, state: dict) -> None:
        self._env.set_rng_state(state)

    def reset(self) -> TimeStep:
        frame, _, _, _ = self._env.reset()
        self._frames.extend([frame] * self.k)
        return TimeStep(self._stack(), frame, 0.0, 1.0, True, False)

    def step(self, action: np.ndarray) -> TimeStep:
        frame, reward, discount, last = self._env.step(action)
        self._frames.append(frame)
        return TimeStep(self._stack(), frame, float(reward), float(discount), False, last)

    def _stack(self) -> np.ndarray:
        return np.concatenate(self._frames, axis=0)


def make(
    task: str,
    seed: int,
    frame_stack: int = 3,
    action_repeat: int = 1,
    image_size: int = 84,
    camera_id: int = 0,
    render_quality: RenderQuality = "paper",
) -> FrameStack:
    """The pixel environment every actor and the trainer step."""
    pixels = DMCPixels(task, seed, image_size, camera_id, action_repeat, render_quality)
    return FrameStack(pixels, frame_stack)


def stored_discount(ts: TimeStep, time_limit: Literal["bootstrap", "terminal"]) -> float:
    """The discount a transition is stored with.

    `bootstrap` keeps the suite's discount (1.0 at a time-limit ending, so the
    critic bootstraps through it, as SAC-AE does); `terminal` reproduces the
    NaSA-TD3 reference, which treats every episode end as terminal.
    """
    if time_limit == "terminal" and ts.last:
        return 0.0
    return ts.discount


def from_config(config: EnvConfig, seed: int) -> FrameStack:
    """The environment an `EnvConfig` describes (trainer, actors and evaluator alike)."""
    c = config
    return make(c.task, seed, c.frame_stack, c.action_repeat, c.image_size, c.camera_id, c.render_quality)
