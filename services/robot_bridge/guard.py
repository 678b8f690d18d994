"""The torque guard: turns the servos' torque off when the bridge dies by any means.

The XL-320 has no bus watchdog: a bridge that is SIGKILLed, OOM-killed or crashes leaves its
servos holding torque. `TorqueGuard` (in the bridge) starts this module as a process of its own
session, so a Ctrl-C to the terminal's process group or a kill of the bridge alone leaves it
running, with the read end of a pipe whose write end only the bridge holds. The guard sleeps in
a blocking read on it. On a clean stop the bridge turns torque off itself, then writes the
stand-down byte: the guard exits without touching the bus. EOF without it means the bridge is
gone: the guard opens the port by name (retrying while it is still held or gone), writes Torque
Enable = 0 to every servo through the bridge's own driver, logs one line and exits; its tries
are bounded, so it never hangs.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Sequence

from services.robot_bridge.dynamixel import BusError, ServoBus
from shared.service import Log

STAND_DOWN = b"s"
READY = b"ready\n"
READY_TIMEOUT_S = 60.0  # the guard imports the driver (numpy, dynamixel-sdk) before it is ready
EXIT_WAIT_S = 5.0
ATTEMPTS = 5
RETRY_PAUSE_S = 0.5


class GuardUnavailable(RuntimeError):
    """The guard process did not start: the bridge must not take torque without it."""


class TorqueGuard:
    """The bridge's side: starts the guard process, and stands it down on a clean stop."""

    def __init__(self, port: str, baud: int, ids: Sequence[int], latency_ms: float) -> None:
        read_end, self._write_end = os.pipe()  # not inherited by anything else the bridge starts
        argv = [sys.executable, "-m", "services.robot_bridge.guard", "--fd", str(read_end), "--port", port,
                "--baud", str(baud), "--latency-ms", str(latency_ms), "--ids", ",".join(map(str, ids))]
        try:
            # stderr is the bridge's: the guard's line lands wherever the bridge logs.
            self.process = subprocess.Popen(argv, pass_fds=(read_end,), start_new_session=True,
                                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
        except OSError as err:
            os.close(self._write_end)
            raise GuardUnavailable(f"cannot start the torque guard: {err}") from err
        finally:
            os.close(read_end)
        self._wait_ready()

    def _wait_ready(self) -> None:
        out = self.process.stdout
        assert out is not None
        try:
            ready, _, _ = select.select([out], [], [], READY_TIMEOUT_S)
            line = out.readline() if ready else b""
        finally:
            out.close()
        if line != READY:
            self.close(stand_down=False)
            self.process.kill()
            self.process.wait()
            raise GuardUnavailable(f"the torque guard did not start (exit status {self.process.returncode})")

    def close(self, stand_down: bool) -> None:
        """Stand the guard down (torque is off: the bridge turned it off itself) and wait for it to
        exit; without `stand_down` the guard turns torque off itself, as if the bridge had died."""
        if self._write_end < 0:
            return
        try:
            if stand_down:
                os.write(self._write_end, STAND_DOWN)
        except OSError:
            pass  # the guard is gone already
        finally:
            os.close(self._write_end)
            self._write_end = -1
        if stand_down:
            try:
                self.process.wait(timeout=EXIT_WAIT_S)
            except subprocess.TimeoutExpired:
                pass  # it exits on its own once it reads the word


def torque_off(port: str, baud: int, ids: Sequence[int], latency_ms: float,
               attempts: int = ATTEMPTS, pause_s: float = RETRY_PAUSE_S) -> tuple[list[int], str]:
    """Torque Enable = 0 on every servo, each acknowledged; returns those it could not reach and why."""
    left, why = list(ids), ""
    for attempt in range(attempts):
        if attempt:
            time.sleep(pause_s)
        try:
            bus = ServoBus(port, baud, left, latency_ms)
        except BusError as err:  # the dead bridge's port is not free yet, or the adapter is gone
            why = str(err)
            continue
        try:
            for sid in list(left):
                try:
                    bus.set_torque(False, [sid])
                    left.remove(sid)
                except BusError as err:
                    why = str(err)
        finally:
            bus.close()
        if not left:
            break
    return left, why


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robot_bridge.guard", description=__doc__.splitlines()[0])
    parser.add_argument("--fd", type=int, required=True, help="the read end of the bridge's pipe")
    parser.add_argument("--port", required=True)
    parser.add_argument("--baud", type=int, required=True)
    parser.add_argument("--latency-ms", type=float, required=True)
    parser.add_argument("--ids", required=True, help="the servo ids, comma separated")
    args = parser.parse_args(argv)
    ids = [int(sid) for sid in args.ids.split(",")]
    log = Log("torque guard")
    # A stop signal meant for the bridge's whole group (systemd's stop, a hang-up) must not take the
    # guard first: it ends on its own, once the bridge stands it down or dies and its tries end.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    sys.stdout.buffer.write(READY)
    sys.stdout.flush()
    devnull = os.open(os.devnull, os.O_WRONLY)  # the bridge reads the ready line only
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    try:
        word = os.read(args.fd, 1)  # blocks, without polling, until the word or the bridge's death
    except OSError as err:
        word, error = b"", err
    else:
        error = None
    if word == STAND_DOWN:
        return 0
    why = f"cannot read its pipe ({error})" if error else "the bridge died"
    unreached, failure = torque_off(args.port, args.baud, ids, args.latency_ms)
    if unreached:
        log(f"{why}: could not turn torque off on servos {unreached} at {args.port} after {ATTEMPTS} "
            f"tries ({failure}); cut the servos' power")
        return 1
    log(f"{why}: turned torque off on servos {ids} at {args.port}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
