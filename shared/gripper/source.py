"""The gripper as an environment source: the stand-in in-process, or a robot bridge over Zenoh.

`GripperSource` follows `shared.envs.EnvSource` (name, tasks, spec, make); `register()` it in
`shared/envs.py` and every command takes `gripper-valve` and `gripper-valve_reset`. `make()`
steps the MuJoCo stand-in in the calling process; `make_remote()` steps whatever a bridge
serves (the stand-in in its own process, or the real gripper) and checks it is the task asked for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from shared.config import ConfigError
from shared.gripper import ACTION_DIM, TASK_NAMES, frame_shape

if TYPE_CHECKING:
    from shared.config import EnvConfig


class BridgeMismatch(ConfigError):
    """The bridge serves another task or frame size than the run's config (bad input: a service
    that meets it exits 2 rather than restarting into the same mismatch)."""


class GripperSource:
    name = "gripper"

    def tasks(self) -> list[str]:
        return list(TASK_NAMES)

    def spec(self, config: EnvConfig) -> Any:
        from shared.envs import EnvSpec

        return EnvSpec(frame_shape(config.image_size), config.frame_stack, ACTION_DIM)

    def make(self, config: EnvConfig, seed: int) -> Any:
        from shared.envs import FrameStack
        from shared.gripper.sim import ValveSim

        c = config
        pixels = ValveSim(c.task, seed, c.image_size, c.camera_id, c.action_repeat, c.render_quality)
        return FrameStack(pixels, c.frame_stack)

    def make_remote(self, config: EnvConfig, session: Any, bridge_id: str, client: str,
                    timeout_s: float = 30.0) -> Any:
        """The bridge's environment, stacked here; the bridge keeps its own seed and render settings.
        `client`: who asks (`services.robot_bridge.client.client_name`), as the bridge serves one
        client at a time."""
        from services.robot_bridge.client import BridgeEnv
        from shared import envs
        from shared.envs import FrameStack

        envs.check_remote(config, BridgeMismatch)
        remote = BridgeEnv(session, bridge_id, client=client, timeout_s=timeout_s)
        if remote.task != config.task or remote.frame_shape != frame_shape(config.image_size):
            raise BridgeMismatch(
                f"bridge {bridge_id} serves {remote.task} at {list(remote.frame_shape)}; the run asks for "
                f"{config.task} at {list(frame_shape(config.image_size))}"
            )
        return FrameStack(remote, config.frame_stack)
