"""Pixel environments behind one seam: environment sources, a spec, and `from_config`.

An environment *source* owns a set of task names and knows, for each, the
environment's spec (frame shape, frame stack, action size) without rendering,
and how to build it. `spec()`, `check_task()` and `from_config()` find the
source by the task name, so a new source (the gripper bridge, say) is one
object passed to `register()`: nothing that reads a spec or steps a
`PixelEnv` changes. The one source today is `dmc`, the DeepMind Control Suite.

A source's environment is composed of thin layers the way DrQ-v2's `dmc.py`
does: the task, a pixel renderer with action repeat, and a frame stack that
stacks the last k frames along channels. Every `PixelEnv` exposes the same
interface, so actors and the trainer never care which one they hold, and a
service that does not step an environment reads its `EnvSpec` from the run's
config instead of building one.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

from shared import gl

gl.configure()  # before dm_control loads a GL backend

if TYPE_CHECKING:
    from shared.config import EnvConfig

PAPER_TASKS = (
    "ball_in_cup-catch",
    "cartpole-balance",
    "reacher-hard",
    "finger-spin",
    "walker-walk",
    "cheetah-run",
)


class UnknownTaskError(ValueError):
    """A task name that no environment source owns."""


class EnvUnavailable(RuntimeError):
    """A remote environment (a robot bridge) is gone or refuses for now: the episode under way
    is abandoned, and the caller starts a new one once the environment is back."""


class EnvFault(ValueError):
    """The episode under way cannot go on: the simulation diverged (MuJoCo's PhysicsError) or the
    policy's action is not finite. The episode is lost; a reset starts a sound one."""

ACTION_BOUND = 1.0
"""Every task's actions lie in [-ACTION_BOUND, ACTION_BOUND]; the wire and the replay refuse others."""
RESET_TRIES = 3
"""Initial states a suite task draws before its reset is an EnvFault: a drawn state the simulation
cannot hold (MuJoCo's PhysicsError at reset) is drawn again."""


@dataclass(frozen=True)
class EnvSpec:
    """What a learner, a replay or a network needs to know about an environment."""

    frame_shape: tuple[int, int, int]
    """(C, H, W) of one rendered frame, uint8."""
    frame_stack: int
    action_dim: int
    """Actions are float vectors in [-1, 1] of this size."""

    def __post_init__(self) -> None:
        # Normalise lists (from JSON or msgpack) to tuples, so equal specs compare equal.
        object.__setattr__(self, "frame_shape", tuple(int(n) for n in self.frame_shape))
        if len(self.frame_shape) != 3 or min(self.frame_shape) < 1:
            raise ValueError(f"frame_shape must be (C, H, W) of positive sizes, got {self.frame_shape}")
        if self.frame_stack < 1 or self.action_dim < 1:
            raise ValueError(f"frame_stack and action_dim must be >= 1, got {self.frame_stack}, "
                             f"{self.action_dim}")

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        """(C * k, H, W): the last k frames stacked along channels."""
        c, h, w = self.frame_shape
        return (c * self.frame_stack, h, w)

    def to_dict(self) -> dict:
        return {"frame_shape": list(self.frame_shape), "frame_stack": self.frame_stack,
                "action_dim": self.action_dim}

    @classmethod
    def from_dict(cls, d: dict) -> EnvSpec:
        return cls(tuple(d["frame_shape"]), int(d["frame_stack"]), int(d["action_dim"]))


@dataclass(frozen=True)
class TimeStep:
    """One environment step as seen by an agent.

    `frame` is the newest rendered frame (C, H, W); `obs` is the stack of the
    last `frame_stack` frames along channels. `discount` is the source's: 1.0 at
    a time-limit ending, 0.0 at a true terminal.
    """

    obs: np.ndarray
    frame: np.ndarray
    reward: float
    discount: float
    first: bool
    last: bool


class PixelEnv(Protocol):
    spec: EnvSpec
    action_dim: int
    obs_shape: tuple[int, int, int]

    def reset(self) -> TimeStep: ...
    def step(self, action: np.ndarray) -> TimeStep: ...
    def rng_state(self) -> dict: ...
    def set_rng_state(self, state: dict) -> None: ...


class Pixels(Protocol):
    """One rendered frame per step (what `FrameStack` stacks): a source's bottom layer."""

    frame_shape: tuple[int, int, int]
    action_dim: int

    def reset(self) -> tuple[np.ndarray, float, float, bool]: ...
    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]: ...
    def rng_state(self) -> dict: ...
    def set_rng_state(self, state: dict) -> None: ...


class EnvSource(Protocol):
    """A family of environments: its task names, their spec, and how to build one."""

    name: str

    def tasks(self) -> list[str]: ...
    def spec(self, config: EnvConfig) -> EnvSpec: ...
    def make(self, config: EnvConfig, seed: int) -> PixelEnv: ...


_SOURCES: list[EnvSource] = []


def register(source: EnvSource) -> EnvSource:
    """Add an environment source. Its task names are read only when a task is looked up
    (listing the suite's imports dm_control), and must not be another source's."""
    if any(s.name == source.name for s in _SOURCES):
        raise ValueError(f"an environment source named {source.name!r} is already registered")
    _SOURCES.append(source)
    return source


def sources() -> list[EnvSource]:
    return list(_SOURCES)


def all_task_names() -> list[str]:
    """Every task of every source, sorted."""
    return sorted(t for s in _SOURCES for t in s.tasks())


def source_for(task: str) -> EnvSource:
    """The source that owns `task`; UnknownTaskError lists every valid name."""
    for source in _SOURCES:
        if task in source.tasks():
            return source
    raise UnknownTaskError(f"unknown task {task!r}; valid tasks are: {', '.join(all_task_names())}")


def check_task(name: str) -> None:
    """Raise UnknownTaskError (listing every valid name of every source) unless a source owns `name`."""
    source_for(name)


def check_remote(config: EnvConfig, error: type[Exception] | None = None) -> None:
    """Raise `error` (default ConfigError) unless a robot bridge can serve `config`: a task whose
    source steps it remotely, one action per step (a bridge step is one command to the servos)."""
    from shared.config import ConfigError

    error = error or ConfigError
    if not hasattr(source_for(config.task), "make_remote"):
        raise error(f"{config.task} is not a task a robot bridge serves (gripper-*)")
    if config.action_repeat != 1:
        raise error(f"a robot bridge steps one action at a time: --action-repeat 1, "
                    f"not {config.action_repeat}")


def check_camera(config: EnvConfig) -> None:
    """Raise ConfigError unless `config.camera_id` is a camera of the task's MuJoCo model: a bad one
    fails only at the first render, after the run folder is written. Loads the model, renders nothing."""
    from shared.config import ConfigError

    source = source_for(config.task).name
    if source == "dmc":
        count = _load_suite_task(config.task, 0).physics.model.ncam
    elif source == "gripper":
        import mujoco

        from shared.gripper.sim import MODEL_PATH

        count = mujoco.MjModel.from_xml_path(str(MODEL_PATH)).ncam
    else:
        return  # a source of its own: its make() checks
    if not 0 <= config.camera_id < count:
        raise ConfigError(f"env.camera_id {config.camera_id} is not a camera of {config.task}: its model "
                          f"has {count} (ids 0 to {count - 1})")


def spec(config: EnvConfig) -> EnvSpec:
    """The spec of the environment `config` describes, from its source; renders nothing."""
    return source_for(config.task).spec(config)


def from_config(config: EnvConfig, seed: int) -> PixelEnv:
    """The environment an `EnvConfig` describes (trainer, actors and evaluator alike)."""
    return source_for(config.task).make(config, seed)


# -- the DeepMind Control Suite -------------------------------------------------------


def all_tasks() -> list[str]:
    """The suite's task names, `domain-task`."""
    from dm_control import suite

    return sorted(f"{domain}-{task}" for domain, task in suite.ALL_TASKS)


def parse_task(name: str) -> tuple[str, str]:
    """Split a suite task `domain-task`, failing with the list of valid names."""
    if name not in all_tasks():
        check_task(name)  # owned by another source, or unknown: the error lists every name
        raise UnknownTaskError(f"task {name!r} is not a DeepMind Control Suite task")
    domain, task = name.split("-", 1)
    return domain, task


def _load_suite_task(task: str, seed: int):  # noqa: ANN202 (a dm_control environment)
    from dm_control import suite

    domain, task_name = parse_task(task)
    env = suite.load(domain, task_name, task_kwargs={"random": seed})
    bounds = env.action_spec()
    if not (np.all(bounds.minimum == -ACTION_BOUND) and np.all(bounds.maximum == ACTION_BOUND)):
        raise ValueError(f"task {task} has actions outside [-{ACTION_BOUND:g}, {ACTION_BOUND:g}]: {bounds}")
    return env


class DMCPixels:
    """A suite task rendered to (3, H, W) uint8 frames, with action repeat."""

    def __init__(
        self,
        task: str,
        seed: int,
        image_size: int = 84,
        camera_id: int = 0,
        action_repeat: int = 1,
        render_quality: gl.RenderQuality = "paper",
    ) -> None:
        if action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        from dm_control.rl.control import PhysicsError

        self._env = _load_suite_task(task, seed)
        self._physics_error = PhysicsError
        gl.apply_render_quality(self._env.physics.model, render_quality)
        self.action_dim = int(self._env.action_spec().shape[0])
        self.image_size = image_size
        self.frame_shape = (3, image_size, image_size)
        self.camera_id = camera_id
        self.action_repeat = action_repeat
        self._camera = None
        self._camera_physics = None

    def render(self) -> np.ndarray:
        # One camera for every frame: physics.render builds (and frees) a scene each time;
        # reusing it draws the same pixels with less work. Rebuilt if the task swaps its physics.
        physics = self._env.physics
        if self._camera is None or self._camera_physics is not physics:
            from dm_control.mujoco import Camera

            from shared.checkpoint import stop_signals_deferred

            # A Ctrl-C inside the GL context's making leaves half a context, whose teardown then
            # prints a traceback of its own: the interrupt waits until it is made.
            with stop_signals_deferred():
                self._camera = Camera(physics, self.image_size, self.image_size, self.camera_id)
                self._camera_physics = physics
        return np.ascontiguousarray(self._camera.render().transpose(2, 0, 1))

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
        # Each try draws a new initial state from the task's random stream, so a resumed run
        # draws the same ones.
        for _ in range(RESET_TRIES):
            try:
                self._env.reset()
                return self.render(), 0.0, 1.0, False
            except self._physics_error as err:
                error = err
        raise EnvFault(f"the simulation diverged at each of {RESET_TRIES} resets: {error}") from error

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action shape {action.shape}, expected ({self.action_dim},)")
        if not np.all(np.isfinite(action)):
            raise EnvFault(f"action has non-finite values: {action}")
        reward, discount = 0.0, 1.0
        for _ in range(self.action_repeat):
            try:
                ts = self._env.step(action)
            except self._physics_error as err:
                raise EnvFault(f"the simulation diverged: {err}") from err
            reward += ts.reward or 0.0
            discount *= ts.discount if ts.discount is not None else 1.0
            if ts.last():
                break
        return self.render(), reward, discount, ts.last()


class FrameStack:
    """Stacks the last k frames along channels; an episode starts with its first frame k times."""

    def __init__(self, env: Pixels, k: int = 3) -> None:
        if k < 1:
            raise ValueError(f"frame_stack must be >= 1, got {k}")
        self._env = env
        self._frames: deque[np.ndarray] = deque(maxlen=k)
        self.k = k
        self.spec = EnvSpec(env.frame_shape, k, env.action_dim)
        self.action_dim = env.action_dim
        self.obs_shape = self.spec.obs_shape

    @property
    def pixels(self) -> Pixels:
        """The layer below, which renders each frame (a suite task, the stand-in, a robot bridge)."""
        return self._env

    def fault(self) -> str | None:
        """The environment's fault state where it reports one (a robot bridge); None otherwise."""
        fault = getattr(self._env, "fault", None)
        return fault() if fault is not None else None

    def rng_state(self) -> dict:
        return self._env.rng_state()

    def set_rng_state(self, state: dict) -> None:
        self._env.set_rng_state(state)

    def close(self) -> None:
        """Release the layer below's renderer where it has one (the stand-in's GL context)."""
        close = getattr(self._env, "close", None)
        if close is not None:
            close()

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
    render_quality: gl.RenderQuality = "paper",
) -> FrameStack:
    """A suite task as a PixelEnv (what the `dmc` source builds)."""
    pixels = DMCPixels(task, seed, image_size, camera_id, action_repeat, render_quality)
    return FrameStack(pixels, frame_stack)


class DmcSource:
    """The DeepMind Control Suite: tasks `domain-task`, rendered by MuJoCo."""

    name = "dmc"

    def __init__(self) -> None:
        self._tasks: list[str] | None = None

    def tasks(self) -> list[str]:
        if self._tasks is None:
            self._tasks = all_tasks()
        return self._tasks

    def spec(self, config: EnvConfig) -> EnvSpec:
        # Loading the task builds its physics (to read the action spec) but no GL context.
        action_dim = int(_load_suite_task(config.task, 0).action_spec().shape[0])
        size = config.image_size
        return EnvSpec((3, size, size), config.frame_stack, action_dim)

    def make(self, config: EnvConfig, seed: int) -> FrameStack:
        c = config
        return make(c.task, seed, c.frame_stack, c.action_repeat, c.image_size, c.camera_id, c.render_quality)


DMC = register(DmcSource())


def _register_gripper() -> EnvSource:
    from shared.gripper.source import GripperSource  # the valve stand-in and the robot bridge

    return register(GripperSource())


GRIPPER = _register_gripper()


def stored_discount(ts: TimeStep, time_limit: Literal["bootstrap", "terminal"]) -> float:
    """The discount a transition is stored with.

    `bootstrap` keeps the source's discount (1.0 at a time-limit ending, so the
    critic bootstraps through it, as SAC-AE does); `terminal` reproduces the
    NaSA-TD3 reference, which treats every episode end as terminal.
    """
    if time_limit == "terminal" and ts.last:
        return 0.0
    return ts.discount
