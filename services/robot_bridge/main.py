"""`python -m services.robot_bridge`: one process per gripper, serving it (or its stand-in) over Zenoh.

Without `--config` it serves the MuJoCo stand-in (`shared/gripper`); with a gripper config file it
serves the real servos and camera; with `--emulate`, the real gripper's code path (driver and
interlocks) against an emulated servo bus in this process, with a drawn camera (`emulated.py`).
SIGINT and SIGTERM e-stop the gripper (torque off) before the process exits; the `estop` key
e-stops it without ending the process, until a re-arm message.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from services.robot_bridge.camera import CameraUnavailable
from services.robot_bridge.config import GripperConfigError
from services.robot_bridge.dynamixel import BusError
from services.robot_bridge.guard import GuardUnavailable
from services.robot_bridge.hold import DEFAULT_HOLD_S
from shared import faults, wire
from shared.gl import RenderQuality
from shared.gripper.sim import UnknownGripperTask
from shared.service import (
    EXIT_BAD_INPUT,
    EXIT_LOGIN_REFUSED,
    FlagError,
    Log,
    StopFlag,
    die_with_parent,
    read_flags,
)
from shared.zenoh_session import env_connect


@dataclass
class BridgeArgs:
    bridge_id: str = "0"
    """The bridge's name: its keys are nasa/bridge/<bridge_id>/..."""
    task: Literal["gripper-valve", "gripper-valve_reset"] = "gripper-valve"
    """Scenario 1 (valve left where it is) or 2 (turned to a random angle at each reset)."""
    config: Path | None = None
    """The real gripper's TOML config (services/robot_bridge/example.toml); none: the stand-in."""
    emulate: bool = False
    """Without --config: the hardware path (dynamixel-sdk, interlocks) against an emulated bus on a
    pty and a drawn camera, instead of the MuJoCo stand-in."""
    seed: int = 0
    """Draws targets and reset angles."""
    image_size: int = 84
    camera_id: int = 0
    """The stand-in's MuJoCo camera (the run's env.camera_id). The emulated and the real camera are
    the only ones there: any other id is refused."""
    render_quality: RenderQuality = "fast"
    """The stand-in's render quality."""
    client_hold_s: float = DEFAULT_HOLD_S
    """The bridge serves one client at a time: another client's reset is refused until the one it
    serves has been silent this long (seconds), then the next to reset takes the gripper."""
    connect: str = field(default_factory=env_connect)
    """Zenoh router endpoint(s) (env NASA_ZENOH_CONNECT)."""


def build_env(args: BridgeArgs):
    if (args.config is not None or args.emulate) and args.camera_id != 0:
        raise ValueError(f"--camera-id {args.camera_id}: the stand-in's camera; the emulated and the real "
                         "gripper have one camera each (id 0)")
    if args.config is None and args.emulate:
        from services.robot_bridge.emulated import EmulatedGripper

        return EmulatedGripper(args.task, args.seed, image_size=args.image_size)
    if args.config is None:
        from shared.gripper.sim import ValveSim

        return ValveSim(args.task, args.seed, image_size=args.image_size, camera_id=args.camera_id,
                        render_quality=args.render_quality)
    from services.robot_bridge.config import load
    from services.robot_bridge.hardware import GripperHardware

    return GripperHardware(load(args.config), args.task, args.seed)


def main(argv: list[str] | None = None) -> None:
    from services.robot_bridge.server import BridgeServer
    from shared.zenoh_session import RouterUnreachable, SessionRefused, open_client

    die_with_parent()
    try:
        args = read_flags(BridgeArgs, sys.argv[1:] if argv is None else argv,
                          "python -m services.robot_bridge")
        if not (math.isfinite(args.client_hold_s) and args.client_hold_s > 0):
            raise FlagError(f"--client-hold-s must be a finite number > 0, got {args.client_hold_s}")
    except FlagError as err:
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    log = Log(f"bridge {args.bridge_id}")
    try:
        env = build_env(args)
    except (GripperConfigError, UnknownGripperTask, ValueError) as err:
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    except (GuardUnavailable, BusError, CameraUnavailable) as err:
        # No torque without the guard; an adapter or a camera not there yet may come (re-plugged):
        # exit 1, its supervisor retries.
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
    stop = StopFlag()
    stop.install_signal_handlers()
    try:
        with open_client(args.connect, role="bridge") as session:
            # Two bridges of one id would both answer every step: one policy would drive two grippers.
            key = wire.BridgeKeys(args.bridge_id).alive
            hint = "stop that one first, or give this one its own --bridge-id"
            if faults.claim_role(session, key, stop, log, f"bridge {args.bridge_id}", hint):
                server = BridgeServer(session, args.bridge_id, env, args.task, log=log,
                                      hold_s=args.client_hold_s)
                with server.serve():
                    kind = "hardware" if args.config else "emulated bus" if args.emulate else "stand-in"
                    log(f"serving {args.task} ({kind}) on {server.keys.prefix}")
                    guard = getattr(env, "guard", None)
                    if guard is not None:
                        log(f"torque guard running (pid {guard.process.pid})")
                    while not stop.wait(0.2):
                        pass
                    server.estop(f"{stop.reason}: bridge stopping")  # torque off before the process goes
            log(f"stopped ({stop.reason})")
    except faults.RoleTaken as err:
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    except SessionRefused as err:  # the same credentials would be refused again: not restarted
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_LOGIN_REFUSED)
    except RouterUnreachable as err:  # exit 1: its supervisor retries
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
    finally:
        env.close()
    stop.exit_if_signalled()
