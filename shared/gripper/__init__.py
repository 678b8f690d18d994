"""The gripper valve task: names and shapes known without building anything (for an EnvSpec).

`shared.gripper.sim.ValveSim` is the MuJoCo stand-in; `services.robot_bridge` serves it or the
real gripper over Zenoh. Importing this package loads no MuJoCo.
"""

TASK_NAMES: tuple[str, ...] = ("gripper-valve", "gripper-valve_reset")
"""`gripper-valve`: the valve stays where it is between episodes; `gripper-valve_reset`: a servo
turns it to a random angle at each reset."""
ACTION_DIM = 4
"""One goal position per finger servo, each in [-1, 1]."""


def frame_shape(image_size: int) -> tuple[int, int, int]:
    """The (C, H, W) of one frame, stand-in or camera."""
    return (3, image_size, image_size)
