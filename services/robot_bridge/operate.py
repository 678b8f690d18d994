"""Operator commands: e-stop and re-arm a bridge over Zenoh, and read the raw valve angle to calibrate.

    python -m services.robot_bridge.operate estop --bridge-id 0
    python -m services.robot_bridge.operate rearm --bridge-id 0
    python -m services.robot_bridge.operate calibrate --config gripper.toml

`calibrate` prints the raw angle reading (ArUco marker or valve servo) with the valve at the angle
you want as 0: put that number in the config's `angle.zero_deg`.
"""

from __future__ import annotations

import argparse
import statistics
import sys

from shared import wire
from shared.zenoh_session import env_connect


def send_estop(bridge_id: str, engage: bool, reason: str, connect: str) -> None:
    from shared.zenoh_session import open_client

    # An operator waiting on an e-stop must hear within seconds that it did not go out.
    with open_client(connect, timeout_s=5.0, role="operator") as session:
        session.put(wire.BridgeKeys(bridge_id).estop, wire.encode(wire.BridgeEStop(engage, reason)))


def raw_reading(config_path: str, samples: int, source: str | None = None) -> float | None:
    """The median raw valve angle (degrees) over `samples` frames or reads, None if never seen."""
    from services.robot_bridge import xl320
    from services.robot_bridge.camera import ArucoAngle, Camera
    from services.robot_bridge.config import load
    from services.robot_bridge.dynamixel import ServoBus

    config = load(config_path)
    readings: list[float] = []
    if config.angle.source == "aruco":
        camera = Camera(config.camera, source=source)
        sensor = ArucoAngle(config.angle)
        try:
            for _ in range(samples):
                raw = sensor.raw_degrees(camera.frame())
                if raw is not None:
                    readings.append(raw % 360.0)
        finally:
            camera.close()
    else:
        bus = ServoBus(config.bus.port, config.bus.baud, [config.valve.id], config.bus.latency_ms)
        try:
            for _ in range(samples):
                position = bus.read(config.valve.id, xl320.PRESENT_POSITION, 2)
                readings.append(position * xl320.DEGREES_PER_STEP)
        finally:
            bus.close()
    return statistics.median(readings) if readings else None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("estop", "rearm"):
        p = sub.add_parser(name)
        p.add_argument("--bridge-id", default="0")
        p.add_argument("--reason", default=f"operator {name}")
        p.add_argument("--connect", default=env_connect())
    p = sub.add_parser("calibrate")
    p.add_argument("--config", required=True)
    p.add_argument("--samples", type=int, default=15)
    p.add_argument("--source", default=None, help="a video file instead of the configured camera")
    args = parser.parse_args(argv)
    if args.command in ("estop", "rearm"):
        from shared.zenoh_session import RouterUnreachable

        try:
            send_estop(args.bridge_id, args.command == "estop", args.reason, args.connect)
        except RouterUnreachable as err:
            print(f"NOT sent: {args.command} to bridge {args.bridge_id}: {err}", file=sys.stderr, flush=True)
            sys.exit(1)
        print(f"sent {args.command} to bridge {args.bridge_id}")
        return
    raw = raw_reading(args.config, args.samples, args.source)
    if raw is None:
        print("the valve angle was never read: is the marker in view (or the valve servo answering)?")
        sys.exit(1)
    print(f"raw valve angle: {raw:.1f} degrees; with the valve at its zero, set angle.zero_deg = {raw:.1f}")


if __name__ == "__main__":
    main()
