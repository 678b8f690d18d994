"""Operator commands: e-stop and re-arm a bridge over Zenoh, and read the raw valve angle to calibrate.

    python -m services.robot_bridge.operate estop --bridge-id 0
    python -m services.robot_bridge.operate rearm --bridge-id 0
    python -m services.robot_bridge.operate calibrate --config gripper.toml

`estop` and `rearm` wait for the bridge's acknowledgement and say who gave it; with none within
--wait-s (no bridge of that id heard it), or one whose state says the command did not take effect
(a re-arm answered `waiting_for_operator`: its recovery failed), they exit 1.

`calibrate` prints the raw angle reading (ArUco marker or valve servo) with the valve at the angle
you want as 0: put that number in the config's `angle.zero_deg`.
"""

from __future__ import annotations

import argparse
import queue
import secrets
import statistics
import sys

from services.robot_bridge.states import REARMED, State
from shared import wire
from shared.zenoh_session import env_connect

ACK_WAIT_S = 5.0
"""How long `estop`/`rearm` wait for the bridge's acknowledgement: its torque-off goes to every
servo, each with its reply timeout, and may wait for a step's bus transfer under way."""


def send_estop(bridge_id: str, engage: bool, reason: str, connect: str,
               wait_s: float = ACK_WAIT_S) -> wire.BridgeEStopAck | None:
    """Send an e-stop (or, `engage` False, a re-arm) to the bridge of that id, then wait up to
    `wait_s` for its acknowledgement; None if no bridge of that id answered."""
    from shared.zenoh_session import open_client

    keys = wire.BridgeKeys(bridge_id)
    request = secrets.token_hex(8)
    acks: queue.Queue[wire.BridgeEStopAck] = queue.Queue()

    def heard(sample) -> None:  # noqa: ANN001 (a zenoh.Sample)
        try:
            ack = wire.decode(sample.payload.to_bytes(), wire.BridgeEStopAck)
        except wire.WireError:
            return  # not an answer this command can read: as if unanswered
        if ack.request == request and ack.engage == engage:  # the answer to this very command
            acks.put(ack)

    # An operator waiting on an e-stop must hear within seconds that it did not go out.
    with open_client(connect, timeout_s=5.0, role="operator") as session:
        # Declared first, so the answer cannot pass before it; the stop goes out right after,
        # and the wait below only reports.
        with session.declare_subscriber(keys.estop_ack, heard):
            session.put(keys.estop, wire.encode(wire.BridgeEStop(engage, reason, request)))
            try:
                return acks.get(timeout=wait_s)
            except queue.Empty:
                return None


def report(command: str, bridge_id: str, ack: wire.BridgeEStopAck | None, wait_s: float) -> tuple[str, bool]:
    """What the operator is told of an `estop`/`rearm`, and whether it took effect."""
    if ack is None:
        what = ("stop the bridge itself (Ctrl-C) or cut the servos' power" if command == "estop"
                else "check that the bridge runs, then send the re-arm again")
        return (f"NOT confirmed: {command} went out, but no bridge {bridge_id} answered within {wait_s:g} s "
                f"(a wrong --bridge-id, a bridge that is down, or one older than this command): check "
                f"the id; {what}", False)
    # Only an answer that says the bridge is stopped confirms a stop; a re-arm, one that it is
    # homing or ready (`waiting_for_operator`: the re-arm's recovery failed before the answer).
    if command == "estop" and ack.state != "estop":
        what = "it is not e-stopped: stop the bridge itself (Ctrl-C) or cut the servos' power"
    elif command == "rearm" and ack.state == "estop":
        what = "it is still e-stopped: send the re-arm again"
    elif command == "rearm" and ack.state == State.WAITING_FOR_OPERATOR:
        what = ("its recovery failed (torque off, resets refused): clear the fault its replies name "
                "under safety, then send the re-arm again")
    elif command == "rearm" and ack.state not in REARMED:
        what = "a state this command does not know (a newer bridge?): check the bridge before using it"
    else:
        what = ""
    if what:
        return (f"NOT confirmed: bridge {bridge_id} ({ack.bridge}) answered the {command} with state "
                f"{ack.state}: {what}", False)
    if ack.unreached:
        return (f"NOT confirmed: bridge {bridge_id} ({ack.bridge}) is e-stopped (state {ack.state}), but "
                f"its torque-off did not reach servos {ack.unreached}: cut the servos' power", False)
    if command == "estop":
        stopped = "stopped (the stand-in: no servos)" if ack.stand_in else "torque off"
        return (f"e-stop confirmed by bridge {bridge_id} ({ack.bridge}): state {ack.state}, "
                f"{stopped}; it refuses steps and resets until re-armed", True)
    return (f"re-arm confirmed by bridge {bridge_id} ({ack.bridge}): state {ack.state}; it homes, "
            "then takes resets", True)


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
        p.add_argument("--wait-s", type=float, default=ACK_WAIT_S,
                       help="how long to wait for the bridge's acknowledgement")
    p = sub.add_parser("calibrate")
    p.add_argument("--config", required=True)
    p.add_argument("--samples", type=int, default=15)
    p.add_argument("--source", default=None, help="a video file instead of the configured camera")
    args = parser.parse_args(argv)
    if args.command in ("estop", "rearm"):
        if not 0.0 <= args.wait_s <= 3600.0:  # NaN too
            parser.error(f"--wait-s {args.wait_s}: seconds, from 0 to 3600")
        try:
            wire.check_run_id(args.bridge_id)  # a bridge's id follows a run id's rule
        except ValueError:
            parser.error(f"--bridge-id {args.bridge_id!r}: an id may hold only letters, digits, "
                         "'_', '.', '-'")
        from shared.zenoh_session import RouterUnreachable

        try:
            ack = send_estop(args.bridge_id, args.command == "estop", args.reason, args.connect, args.wait_s)
        except RouterUnreachable as err:
            print(f"NOT sent: {args.command} to bridge {args.bridge_id}: {err}", file=sys.stderr, flush=True)
            sys.exit(1)
        line, confirmed = report(args.command, args.bridge_id, ack, args.wait_s)
        print(line, file=sys.stdout if confirmed else sys.stderr, flush=True)
        if not confirmed:
            sys.exit(1)
        return
    from services.robot_bridge.camera import CameraUnavailable
    from services.robot_bridge.config import GripperConfigError
    from services.robot_bridge.dynamixel import BusError
    from shared.service import EXIT_BAD_INPUT

    try:
        raw = raw_reading(args.config, args.samples, args.source)
    except (GripperConfigError, BusError, CameraUnavailable) as err:
        # A bad config file is the operator's input (exit 2); a port another process holds, a
        # missing adapter or camera, exit 1.
        print(f"calibrate: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT if isinstance(err, GripperConfigError) else 1)
    if raw is None:
        print("calibrate: error: the valve angle was never read: is the marker in view (or the valve "
              "servo answering)?", file=sys.stderr, flush=True)
        sys.exit(1)
    print(f"raw valve angle: {raw:.1f} degrees; with the valve at its zero, set angle.zero_deg = {raw:.1f}")


if __name__ == "__main__":
    main()
