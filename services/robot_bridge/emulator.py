"""A Dynamixel Protocol 2.0 bus of emulated XL-320 servos on a pseudo-terminal, for tests.

`BusEmulator` opens a pty and answers instruction packets on its master side from a thread
(ping, read, write, sync read, sync write, reboot), with the framing of `protocol`, over an
XL-320 control table per id. The driver opens the slave path as if it were the USB adapter, so
the real `dynamixel-sdk` code path runs unchanged. Emulated servos move toward their goal at
their moving speed while torque is on. Faults are injected per servo: `kill` (stops answering),
`delay` (answers late, so the host times out), `overload` (the overload error bit: torque off
and the alert bit in every status, as the XL-320's shutdown does), `corrupt` (the next
status packets carry a wrong CRC), `garble` (line noise before the next status packets, or each
sent in two parts) and `refuse` (the next instructions answered with an error number and no
data, as a servo answers a packet that reached it corrupted). Like a servo's firmware, it
resynchronises on noise: a header with an impossible length or a bad CRC costs its bytes, never
the packets after it (`protocol.decode`).
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Iterable

from services.robot_bridge import protocol as p
from services.robot_bridge import xl320

_ITEMS = {addr: (size, writable) for _, addr, size, writable, _ in xl320.CONTROL_TABLE}


class EmulatedServo:
    """One XL-320: its control table, and a position that moves toward the goal at its speed."""

    def __init__(self, servo_id: int, position: int = 512) -> None:
        self.table = bytearray(xl320.TABLE_SIZE)
        for _, addr, size, _, initial in xl320.CONTROL_TABLE:
            self.table[addr : addr + size] = initial.to_bytes(size, "little")
        self.table[3] = servo_id
        self.position = float(position)
        self._set(xl320.GOAL_POSITION, position)
        self.dead = False
        self.delay_s = 0.0
        self.corrupt_replies = 0
        self.noise = b""  # written before each of the next `garbled_replies` status packets
        self.split = False
        self.garbled_replies = 0
        self.refuse_number = 0
        self.refused_replies = 0
        self.reboots = 0
        self._sync_outputs()

    @property
    def servo_id(self) -> int:
        return self.table[3]

    def get(self, addr: int) -> int:
        size = _ITEMS[addr][0]
        return int.from_bytes(self.table[addr : addr + size], "little")

    def _set(self, addr: int, value: int) -> None:
        size = _ITEMS[addr][0]
        self.table[addr : addr + size] = int(value).to_bytes(size, "little")

    def advance(self, dt: float) -> None:
        if self.get(xl320.TORQUE_ENABLE):
            low, high = self.get(6), self.get(8)
            goal = min(max(self.get(xl320.GOAL_POSITION), low), high)
            error = goal - self.position
            room = min(abs(error), xl320.steps_per_second(self.get(xl320.MOVING_SPEED)) * dt)
            self.position += room if error > 0 else -room
        self._sync_outputs()

    def _sync_outputs(self) -> None:
        torque = self.get(xl320.TORQUE_ENABLE)
        error = self.get(xl320.GOAL_POSITION) - self.position if torque else 0.0
        self._set(xl320.PRESENT_POSITION, round(self.position))
        self._set(xl320.MOVING, int(abs(error) >= 1.0))
        if self.get(xl320.HARDWARE_ERROR_STATUS) & xl320.ERROR_OVERLOAD:
            load = xl320.TORQUE_MAX
        else:
            # A position servo's load grows with its error: enough to tell a pushing finger.
            load = min(int(abs(error) * 4), xl320.TORQUE_MAX) | (xl320.LOAD_DIRECTION_BIT if error < 0 else 0)
        self._set(xl320.PRESENT_LOAD, load)

    def trip_overload(self) -> None:
        self._set(xl320.HARDWARE_ERROR_STATUS, self.get(xl320.HARDWARE_ERROR_STATUS) | xl320.ERROR_OVERLOAD)
        self._set(xl320.TORQUE_ENABLE, 0)  # the shutdown setting turns torque off on overload
        self._sync_outputs()

    def reboot(self) -> None:
        """Power-cycle: RAM back to its initial values, errors cleared, the shaft where it is."""
        for _, addr, size, _, initial in xl320.CONTROL_TABLE:
            if addr >= xl320.EEPROM_END:
                self.table[addr : addr + size] = initial.to_bytes(size, "little")
        self._set(xl320.GOAL_POSITION, round(self.position))
        self.reboots += 1
        self._sync_outputs()

    def status_error(self, number: int = 0) -> int:
        return number | (p.ALERT if self.get(xl320.HARDWARE_ERROR_STATUS) else 0)

    def read(self, addr: int, length: int) -> tuple[int, bytes]:
        if addr + length > xl320.TABLE_SIZE or length < 1:
            return p.ERR_ACCESS, b""
        return 0, bytes(self.table[addr : addr + length])

    def write(self, addr: int, data: bytes) -> int:
        """Write consecutive items; returns the status error number (0: done)."""
        end = addr + len(data)
        cursor = addr
        while cursor < end:
            if cursor not in _ITEMS:
                return p.ERR_ACCESS
            size, writable = _ITEMS[cursor]
            if not writable or cursor + size > end:
                return p.ERR_ACCESS
            if cursor < xl320.EEPROM_END and self.get(xl320.TORQUE_ENABLE):
                return p.ERR_ACCESS
            cursor += size
        self.table[addr:end] = data
        self._sync_outputs()
        return 0


class BusEmulator:
    """Emulated servos behind a pty; use as a context manager, open `port` with the driver."""

    def __init__(self, ids: Iterable[int], positions: dict[int, int] | None = None) -> None:
        positions = positions or {}
        self.servos = {i: EmulatedServo(i, positions.get(i, 512)) for i in ids}
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._last = time.monotonic()
        self.packets_seen = 0
        self._thread = threading.Thread(target=self._serve, name="dxl-emulator", daemon=True)

    def __enter__(self) -> BusEmulator:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    # -- faults --------------------------------------------------------------------------------
    def kill(self, servo_id: int, dead: bool = True) -> None:
        with self._lock:
            self.servos[servo_id].dead = dead

    def delay(self, servo_id: int, seconds: float) -> None:
        with self._lock:
            self.servos[servo_id].delay_s = seconds

    def overload(self, servo_id: int) -> None:
        with self._lock:
            self.servos[servo_id].trip_overload()

    def corrupt(self, servo_id: int, replies: int = 1) -> None:
        with self._lock:
            self.servos[servo_id].corrupt_replies = replies

    def garble(self, servo_id: int, noise: bytes = b"", split: bool = False, replies: int = 1) -> None:
        """The next `replies` status packets come after `noise`, and in two writes if `split`."""
        with self._lock:
            servo = self.servos[servo_id]
            servo.noise, servo.split, servo.garbled_replies = noise, split, replies

    def refuse(self, servo_id: int, number: int = p.ERR_CRC, replies: int = 1) -> None:
        """The next `replies` instructions are answered with error `number` and no data."""
        with self._lock:
            servo = self.servos[servo_id]
            servo.refuse_number, servo.refused_replies = number, replies

    def snapshot(self, servo_id: int, addr: int) -> int:
        """A control-table value as the servo holds it now (for tests)."""
        with self._lock:
            self._advance()
            return self.servos[servo_id].get(addr)

    # -- serving -------------------------------------------------------------------------------
    def _advance(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        for servo in self.servos.values():
            servo.advance(dt)

    def _serve(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.01)
            with self._lock:
                self._advance()
            if not ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                return
            buffer.extend(chunk)
            while True:
                try:
                    packet = p.decode(buffer)
                except p.BadCrc as bad:
                    self._reply_crc_error(bad.servo_id)
                    continue
                if packet is None:
                    break
                self.packets_seen += 1
                self._handle(packet)

    def _reply_crc_error(self, servo_id: int) -> None:
        servo = self.servos.get(servo_id)
        if servo is not None and not servo.dead:
            self._send(servo, p.status(servo_id, servo.status_error(p.ERR_CRC)))

    def _send(self, servo: EmulatedServo, packet: bytes) -> None:
        if servo.delay_s:
            time.sleep(servo.delay_s)
        if servo.corrupt_replies:
            servo.corrupt_replies -= 1
            packet = packet[:-1] + bytes(((packet[-1] + 1) & 0xFF,))
        if servo.garbled_replies:
            servo.garbled_replies -= 1
            packet = servo.noise + packet
            if servo.split:
                half = len(packet) // 2
                os.write(self._master, packet[:half])
                time.sleep(0.005)  # long enough that the host reads the first part alone
                packet = packet[half:]
        os.write(self._master, packet)

    def _refused(self, servo: EmulatedServo) -> bool:
        """Answer with the injected error number instead of carrying the instruction out."""
        if not servo.refused_replies:
            return False
        servo.refused_replies -= 1
        self._send(servo, p.status(servo.servo_id, servo.status_error(servo.refuse_number)))
        return True

    def _handle(self, packet: p.Packet) -> None:
        with self._lock:
            self._advance()
            if packet.instruction == p.SYNC_WRITE:
                self._sync_write(packet.params)
            elif packet.instruction == p.SYNC_READ:
                self._sync_read(packet.params)
            else:
                servo = self.servos.get(packet.servo_id)
                if servo is not None and not servo.dead and not self._refused(servo):
                    self._single(servo, packet)

    def _single(self, servo: EmulatedServo, packet: p.Packet) -> None:
        sid, params = servo.servo_id, packet.params
        if packet.instruction == p.PING:
            model = xl320.MODEL_NUMBER.to_bytes(2, "little") + bytes((servo.get(2),))
            self._send(servo, p.status(sid, servo.status_error(), model))
        elif packet.instruction == p.READ and len(params) == 4:
            addr, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:], "little")
            number, data = servo.read(addr, length)
            self._send(servo, p.status(sid, servo.status_error(number), data))
        elif packet.instruction == p.WRITE and len(params) >= 3:
            number = servo.write(int.from_bytes(params[:2], "little"), params[2:])
            self._send(servo, p.status(sid, servo.status_error(number)))
        elif packet.instruction == p.REBOOT:
            self._send(servo, p.status(sid, servo.status_error()))
            servo.reboot()
        else:
            self._send(servo, p.status(sid, servo.status_error(p.ERR_INSTRUCTION)))

    def _sync_write(self, params: bytes) -> None:
        addr, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        for i in range(4, len(params) - length, length + 1):
            servo = self.servos.get(params[i])
            if servo is not None and not servo.dead:
                servo.write(addr, params[i + 1 : i + 1 + length])  # broadcast: no status packet

    def _sync_read(self, params: bytes) -> None:
        addr, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        for sid in params[4:]:
            servo = self.servos.get(sid)
            if servo is not None and not servo.dead and not self._refused(servo):
                number, data = servo.read(addr, length)
                self._send(servo, p.status(sid, servo.status_error(number), data))
