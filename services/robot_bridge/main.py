"""`python -m services.robot_bridge`: one process per gripper, serving it (or its stand-in) over Zenoh.

Without `--config` it serves the MuJoCo stand-in (`shared/gripper`); with a gripper config file it
serves the real servos and camera; with `--emulate`, the real gripper's code path (driver and
interlocks) against an emulated servo bus in this process, with a drawn camera (`emulated.py`).
SIGINT and SIGTERM e-stop the gripper (torque off) before the process exits; the `estop` key
e-stops it without ending the process, until a re-arm message.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro

from services.robot_bridge.config import GripperConfigError
from shared.gl import RenderQuality
from shared.gripper.sim import UnknownGripperTask
from shared.service import EXIT_BAD_INPUT, Log, StopFlag, die_with_parent
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
    render_quality: RenderQuality = "fast"
    """The stand-in's render quality."""
    connect: str = field(default_factory=env_connect)
    """Zenoh router endpoint(s) (env NASA_ZENOH_CONNECT)."""


def build_env(args: BridgeArgs):
    if args.config is None and args.emulate:
        from services.robot_bridge.emulated import EmulatedGripper

        return EmulatedGripper(args.task, args.seed, image_size=args.image_size)
    if args.config is None:
        from shared.gripper.sim import ValveSim

        return ValveSim(args.task, args.seed, image_size=args.image_size, render_quality=args.render_quality)
    from services.robot_bridge.config import load
    from services.robot_bridge.hardware import GripperHardware

    return GripperHardware(load(args.config), args.task, args.seed)


TOKEN_LEASE_S = 12.0
"""Longer than Zenoh's default lease (10 s): the token of a bridge whose link died without a close
(a crashed host) is gone by then."""


def _id_free(session, bridge_id: str, stop: StopFlag, log: Log) -> bool:  # noqa: ANN001 (a zenoh.Session)
    """No other process serves this bridge id: its token is not up, or went within TOKEN_LEASE_S (a
    bridge that died just before this restart)."""
    from services.robot_bridge.client import bridge_alive

    deadline = time.monotonic() + TOKEN_LEASE_S
    if not bridge_alive(session, bridge_id, timeout_s=2.0):
        return True
    log(f"bridge {bridge_id}'s token is up: waiting {TOKEN_LEASE_S:.0f} s in case its process just died")
    while time.monotonic() < deadline and not stop.wait(1.0):
        if not bridge_alive(session, bridge_id, timeout_s=2.0):
            return True
    return False


def main(argv: list[str] | None = None) -> None:
    from services.robot_bridge.server import BridgeServer
    from shared.zenoh_session import RouterUnreachable, open_client

    die_with_parent()
    args = tyro.cli(BridgeArgs, args=sys.argv[1:] if argv is None else argv, prog="robot_bridge")
    log = Log(f"bridge {args.bridge_id}")
    try:
        env = build_env(args)
    except (GripperConfigError, UnknownGripperTask, ValueError) as err:
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    stop = StopFlag()
    stop.install_signal_handlers()
    try:
        with open_client(args.connect, role="bridge") as session:
            free = _id_free(session, args.bridge_id, stop, log)
            if stop:
                log(f"stopped ({stop.reason})")
                return
            if not free:
                # Both would answer every step: an actor would drive two grippers with one policy.
                print(f"robot_bridge: error: bridge {args.bridge_id} is already served by another "
                      "process; stop that one first, or give this one its own --bridge-id",
                      file=sys.stderr, flush=True)
                sys.exit(EXIT_BAD_INPUT)
            server = BridgeServer(session, args.bridge_id, env, args.task, log=log)
            with server.serve():
                kind = "hardware" if args.config else "emulated bus" if args.emulate else "stand-in"
                log(f"serving {args.task} ({kind}) on {server.keys.prefix}")
                while not stop.wait(0.2):
                    pass
                server.estop(f"{stop.reason}: bridge stopping")  # torque off before the process goes
            log(f"stopped ({stop.reason})")
    except RouterUnreachable as err:  # exit 1: its supervisor retries
        print(f"robot_bridge: error: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
    finally:
        env.close()
