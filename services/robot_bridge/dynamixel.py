"""The XL-320 servo bus through `dynamixel-sdk` (Protocol 2.0).

`ServoBus` owns the port. Goals go out in one GroupSyncWrite; the state of every servo (present
position, speed, load, voltage, temperature, moving flag and hardware error bits, addresses 37..50)
comes back in one GroupSyncRead, since these are one contiguous block of the XL-320's table.
A failed transfer raises `BusError` naming the servo(s) that did not answer properly, found by
pinging each one, so the bridge's recovery knows which to reboot.

Status packets are parsed here (`_Packets.rxPacket`), not by the SDK's own parser, which lost a
reply behind line noise that looks like a header (a short length failed the transfer at once, a
long one waited out the timeout for bytes that were the reply) and handed a sync read a status
packet without data (a servo refusing the read), which it then indexed past its end, and took a
late answer to an earlier instruction for the reply (a ping's model number read as a position).

The port is locked (`flock`) as it opens: a second program on the bus (a bridge launched twice,
a calibration while a bridge runs) is refused with `PortHeld`, naming the holder.
"""

from __future__ import annotations

import errno
import os
import select
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PortHandler,
)
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler

from services.robot_bridge import xl320
from shared.text import clip

try:
    from termios import error as _TermiosError  # pyserial's input flush raises it on a dead device
except ImportError:  # not a POSIX system
    _TermiosError = OSError
_PORT_FAILURES = (OSError, _TermiosError)


class BusError(RuntimeError):
    """A servo did not answer, answered late, or answered with a corrupt packet."""

    def __init__(self, message: str, servo_ids: Sequence[int]) -> None:
        super().__init__(message)
        self.servo_ids = tuple(servo_ids)


class PortHeld(OSError):
    """Another process holds the port's lock: its packets and ours would interleave on the bus."""


def _port_failure(err: BaseException) -> str:
    """Why a port failed, once. pyserial's text for a port it could not open says the system's
    reason twice ("[Errno 2] could not open port P: [Errno 2] No such file or directory: 'P'"):
    such a failure (it gives an errno to an open's failures only) is the system's reason alone."""
    if isinstance(err, serial.SerialException) and isinstance(err.errno, int):
        return os.strerror(err.errno)
    return str(err)


def _lock_holders(port: str) -> list[str]:
    """The processes holding a lock on the port's device (pid and command line), as /proc/locks
    lists them; none where this system does not."""
    try:
        node = os.stat(port)
        table = Path("/proc/locks").read_text()
    except OSError:
        return []
    device = f"{os.major(node.st_dev):02x}:{os.minor(node.st_dev):02x}:{node.st_ino}"
    holders = []
    for line in table.splitlines():
        fields = [f for f in line.split() if f != "->"]  # "->" marks a lock still waited for
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == device and fields[4].isdigit():
            pid = int(fields[4])
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
            except OSError:
                argv = ""
            command = " ".join(argv.replace("\0", " ").split())  # one line: `python -c` code has newlines
            command = clip(command, 100)
            holders.append(f"pid {pid}: {command}" if command else f"pid {pid}")
    return holders


@dataclass(frozen=True)
class ServoState:
    """One sync read of every servo, in the bus's id order."""

    position: np.ndarray  # steps 0..1023
    load: np.ndarray  # signed, -1023..1023
    moving: np.ndarray  # bool
    error: np.ndarray  # hardware error status bits
    voltage: np.ndarray  # 0.1 V
    temperature: np.ndarray  # degrees C

    def faults(self, ids: Sequence[int]) -> dict[int, list[str]]:
        """The servos whose hardware error bits are set, with the errors' names."""
        return {sid: xl320.error_names(int(bits)) for sid, bits in zip(ids, self.error, strict=True) if bits}


class _Port(PortHandler):
    """The SDK's port with its reply timeout built on a configurable USB latency timer.

    The SDK waits `2 * 16 ms + 2 ms` plus the bytes' transfer time for a reply; adapters whose
    latency timer is set otherwise (or a loaded test machine) need their own figure.
    """

    def __init__(self, port_name: str, latency_ms: float) -> None:
        super().__init__(port_name)
        self.latency_ms = latency_ms

    def getCurrentTime(self) -> float:  # noqa: N802 (the SDK's name)
        """Milliseconds on the monotonic clock. The SDK reads the wall clock, which a clock step (NTP,
        a resumed VM) moves: a step forward failed a transfer whose reply was on its way."""
        return time.monotonic() * 1000.0

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 (the SDK's name)
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.latency_ms * 2.0 + 2.0

    def wait_readable(self) -> None:
        """Block until the port has bytes or the reply window closes. The SDK opens the port with
        a zero read timeout and polls it, which spins a core for the whole wait."""
        left_ms = self.packet_timeout - self.getTimeSinceStart()
        if left_ms > 0:
            select.select([self.ser.fileno()], [], [], left_ms / 1000.0)

    def setupPort(self, cflag_baud: int) -> bool:  # noqa: N802 (the SDK's name)
        """The SDK's, with the port locked as it opens (pyserial takes the lock before it touches
        the port's settings or buffers, so a refused opener changes nothing for the holder). A new
        rate on an open port is set in place: closing it would hand the lock to anyone waiting."""
        if self.is_open:
            self.ser.baudrate = self.baudrate
        else:
            try:
                self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate,
                                         bytesize=serial.EIGHTBITS, timeout=0, exclusive=True)
            except serial.SerialException as err:
                if err.errno not in (errno.EAGAIN, errno.EWOULDBLOCK):
                    raise
                holders = _lock_holders(self.port_name)
                held = f" ({'; '.join(holders)})" if holders else ""
                raise PortHeld(f"in use by another process{held}; a second program on one servo bus "
                               "would interleave its packets with that one's: stop it first") from err
            self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True


_HEADER = bytes((0xFF, 0xFF, 0xFD, 0x00))
_STATUS = 0x55
_MAX_ID = 0xFC
_MIN_LENGTH = 4  # a status packet's length field counts instruction, error and CRC at least
_MAX_LENGTH = 1024 - 7  # the SDK's buffers hold 1,024 bytes, header included
_PING, _READ, _SYNC_READ = 0x01, 0x02, 0x82


class _Packets(Protocol2PacketHandler):
    """Protocol 2.0 with a status-packet parser that resynchronises on noise.

    It scans a stream for the header, takes a length in bounds and a matching CRC, and drops a
    byte and scans on after anything else; an unfinished packet is skipped when a whole valid
    one starts at a later header (a stuffed packet holds no header), so noise whose length field
    covers real replies does not hide them. It checks the timeout at every turn, so a bus that
    never stops talking cannot hold it, and between reads it sleeps on the port until bytes come
    or the reply window closes. A reply has the length its instruction asks for, or is an
    error status without data: a late answer to another instruction is skipped as noise. Bytes
    read past one reply (the next servo's, in a sync
    read) are kept for the next call, and dropped when a new instruction goes out.
    """

    def __init__(self) -> None:
        super().__init__()
        self._pending = bytearray()
        self._corrupt = False  # a packet with a sane header failed its CRC since the last instruction
        self._expected = 0  # the length field of a reply to the last instruction (0: not known)
        self.last_error: dict[int, int] = {}  # each servo's last status error byte

    def txPacket(self, port, txpacket):  # noqa: N802, ANN001, ANN201 (the SDK's name and signature)
        self._pending.clear()  # the SDK clears the port's input as it sends: stale replies go too
        self._corrupt = False
        # The length a reply to this instruction has: a status packet of another length (a late
        # answer to an earlier instruction) is not its reply. An error status has no data.
        instruction = txpacket[7]
        if instruction in (_READ, _SYNC_READ):
            self._expected = _MIN_LENGTH + (txpacket[10] | txpacket[11] << 8)
        else:
            self._expected = {_PING: _MIN_LENGTH + 3}.get(instruction, _MIN_LENGTH)
        return super().txPacket(port, txpacket)

    def _crc_ok(self, packet: bytes | bytearray) -> bool:
        return self.updateCRC(0, packet, len(packet) - 2) == int.from_bytes(packet[-2:], "little")

    def _take(self, max_id: int) -> bytes | None:
        """The first whole valid status packet off the front of the pending bytes (None if none yet)."""
        buf = self._pending
        while True:
            start = buf.find(_HEADER)
            if start < 0:
                del buf[: max(0, len(buf) - 3)]  # keep a possible partial header
                return None
            del buf[:start]
            if len(buf) < 9:
                return None
            length = int.from_bytes(buf[5:7], "little")
            if not self._sane(buf, 0, max_id):
                del buf[:1]
                continue
            end = 7 + length
            if len(buf) < end:
                later = buf.find(_HEADER, 1)
                if later > 0 and self._whole_at(later, max_id):
                    del buf[:later]
                    continue
                return None
            if not self._crc_ok(buf[:end]):
                self._corrupt = True
                del buf[:1]
                continue
            packet = bytes(buf[:end])
            del buf[:end]
            return packet

    def _whole_at(self, start: int, max_id: int) -> bool:
        buf = self._pending
        if len(buf) < start + 9:
            return False
        end = start + 7 + int.from_bytes(buf[start + 5 : start + 7], "little")
        return self._sane(buf, start, max_id) and len(buf) >= end and self._crc_ok(buf[start:end])

    def _sane(self, buf: bytearray, start: int, max_id: int) -> bool:
        """Whether the header at `start` begins a status packet that can answer the last instruction:
        its length is the reply's, or it is an error status (no data)."""
        length = int.from_bytes(buf[start + 5 : start + 7], "little")
        refused = length == _MIN_LENGTH and buf[start + 8] & 0x7F
        fits = length == self._expected or refused if self._expected else _MIN_LENGTH <= length <= _MAX_LENGTH
        return bool(fits) and buf[start + 4] <= max_id and buf[start + 7] == _STATUS

    def rxPacket(self, port, fast_option):  # noqa: N802, ANN001, ANN201 (the SDK's name and signature)
        max_id = 0xFE if fast_option else _MAX_ID
        try:
            while True:
                packet = self._take(max_id)
                if packet is not None:
                    self.last_error[packet[4]] = packet[8]
                    rxpacket = list(packet)
                    return (rxpacket if fast_option else self.removeStuffing(rxpacket)), COMM_SUCCESS
                if port.isPacketTimeout():
                    return [], (COMM_RX_CORRUPT if self._pending or self._corrupt else COMM_RX_TIMEOUT)
                waiting = port.getBytesAvailable()
                if waiting <= 0:
                    port.wait_readable()
                    waiting = port.getBytesAvailable()
                self._pending.extend(port.readPort(waiting if waiting > 0 else 1))
        finally:
            port.is_using = False


class ServoBus:
    """A Protocol 2.0 bus of XL-320 servos on a serial port."""

    def __init__(self, port: str, baud: int, ids: Iterable[int], latency_ms: float = 16.0) -> None:
        self.ids = tuple(ids)
        self.port = _Port(port, latency_ms)
        self.packet = _Packets()
        try:
            # Opened once, at its rate: opened at the SDK's default first and set after, it was
            # closed and opened again in between, when another process could take its lock.
            opened = self.port.setBaudRate(baud)
        except _PORT_FAILURES as err:  # no such device, no access to it, or held by another process
            raise BusError(f"cannot open {port}: {_port_failure(err)}", self.ids) from err
        if not opened:  # a rate the SDK has no setting for: the port is not opened
            raise BusError(f"cannot set {port} to {baud} baud", self.ids)
        self._goals = GroupSyncWrite(self.port, self.packet, xl320.GOAL_POSITION, 2)
        self._reads: dict[tuple[int, ...], GroupSyncRead] = {}
        self._closed = False

    def close(self) -> None:
        self._closed = True
        if self.port.is_open:
            self.port.closePort()

    @contextmanager
    def _port_errors(self, ids: Iterable[int]) -> Iterator[None]:
        """The SDK reads and writes the port directly: a port that fails (pyserial's
        SerialException is an OSError) is a bus error on the servos of the transfer, which every
        caller handles (an unplugged adapter fails its input flush with termios.error, no OSError).
        The SDK marks the port busy for the transfer: it is free again."""
        try:
            if not self.port.is_open:
                # An adapter unplugged and plugged back is a new device under the same name: the
                # old file stays dead, so the port is opened anew (a reopen that fails is an OSError).
                if self._closed:
                    raise BusError(f"{self.port.port_name}: the bus is closed", list(ids))
                self.port.openPort()
            yield
        except _PORT_FAILURES as err:
            self.port.is_using = False
            with suppress(*_PORT_FAILURES):
                self.port.closePort()  # opened again at the next transfer
            raise BusError(f"serial port {self.port.port_name}: {_port_failure(err)}", list(ids)) from err

    # -- whole bus -----------------------------------------------------------------------------
    def write_goals(self, goals: dict[int, int]) -> None:
        """Every servo's goal position in one sync write (broadcast: no reply to check)."""
        self._goals.clearParam()
        for sid, goal in goals.items():
            value = int(goal)
            self._goals.addParam(sid, [value & 0xFF, (value >> 8) & 0xFF])
        with self._port_errors(goals):
            result = self._goals.txPacket()
        if result != COMM_SUCCESS:
            raise BusError(f"sync write failed: {self.packet.getTxRxResult(result)}", list(goals))

    def read_state(self, ids: Sequence[int] | None = None) -> ServoState:
        """The state block of the given servos (all by default), in that order, in one sync read."""
        ids = self.ids if ids is None else tuple(ids)
        group = self._reads.get(ids)
        if group is None:
            group = self._reads[ids] = GroupSyncRead(
                self.port, self.packet, xl320.STATE_BLOCK_START, xl320.STATE_BLOCK_LENGTH
            )
            for sid in ids:
                group.addParam(sid)
        with self._port_errors(ids):
            result = group.txRxPacket()
        if result != COMM_SUCCESS:
            silent = self.unanswering(ids)
            message = self.packet.getTxRxResult(result)
            named = silent or "none"
            raise BusError(f"sync read failed: {message}; servos not answering: {named}", silent or ids)
        short = [sid for sid in ids if len(group.data_dict[sid]) != xl320.STATE_BLOCK_LENGTH]
        if short:
            # A status packet without the data: the servo refused the read (its error says why).
            why = "; ".join(f"servo {sid} answered without its data: "
                            f"{self.packet.getRxPacketError(self.packet.last_error.get(sid, 0) & 0x7F)}"
                            for sid in short)
            raise BusError(f"sync read failed: {why}", short)
        get = group.getData
        return ServoState(
            position=np.array([get(i, xl320.PRESENT_POSITION, 2) for i in ids], dtype=np.int64),
            load=np.array([xl320.signed_load(get(i, xl320.PRESENT_LOAD, 2)) for i in ids], np.int64),
            moving=np.array([bool(get(i, xl320.MOVING, 1)) for i in ids]),
            error=np.array([get(i, xl320.HARDWARE_ERROR_STATUS, 1) for i in ids], dtype=np.int64),
            voltage=np.array([get(i, xl320.PRESENT_VOLTAGE, 1) for i in ids], dtype=np.int64),
            temperature=np.array([get(i, xl320.PRESENT_TEMPERATURE, 1) for i in ids], dtype=np.int64),
        )

    def unanswering(self, ids: Sequence[int] | None = None) -> list[int]:
        """The servos that do not answer a ping properly."""
        return [sid for sid in (self.ids if ids is None else ids) if not self.ping(sid)]

    def set_torque(self, enable: bool, ids: Iterable[int] | None = None) -> None:
        for sid in self.ids if ids is None else ids:
            self.write(sid, xl320.TORQUE_ENABLE, int(enable), 1)

    # -- one servo -----------------------------------------------------------------------------
    def ping(self, servo_id: int) -> bool:
        with self._port_errors([servo_id]):
            model, result, _ = self.packet.ping(self.port, servo_id)
        return result == COMM_SUCCESS and model == xl320.MODEL_NUMBER

    def write(self, servo_id: int, address: int, value: int, size: int) -> None:
        with self._port_errors([servo_id]):
            if size == 1:
                result, error = self.packet.write1ByteTxRx(self.port, servo_id, address, int(value))
            else:
                result, error = self.packet.write2ByteTxRx(self.port, servo_id, address, int(value))
        self._check(servo_id, f"write {value} at {address}", result, error)

    def read(self, servo_id: int, address: int, size: int) -> int:
        with self._port_errors([servo_id]):
            if size == 1:
                value, result, error = self.packet.read1ByteTxRx(self.port, servo_id, address)
            else:
                value, result, error = self.packet.read2ByteTxRx(self.port, servo_id, address)
        self._check(servo_id, f"read at {address}", result, error)
        return int(value)

    def set_limits(self, servo_id: int, moving_speed: int, torque_limit: int) -> None:
        self.write(servo_id, xl320.MOVING_SPEED, moving_speed, 2)
        self.write(servo_id, xl320.TORQUE_LIMIT, torque_limit, 2)

    def hardware_error(self, servo_id: int) -> int:
        return self.read(servo_id, xl320.HARDWARE_ERROR_STATUS, 1)

    def reboot(self, servo_id: int, wait_s: float = 0.5) -> None:
        """Reboot one servo (clears its hardware error; torque comes back off) and wait for it."""
        with self._port_errors([servo_id]):
            result, error = self.packet.reboot(self.port, servo_id)
        self._check(servo_id, "reboot", result, error)
        time.sleep(wait_s)

    def _check(self, servo_id: int, what: str, result: int, error: int) -> None:
        if result != COMM_SUCCESS:
            raise BusError(f"servo {servo_id}: {what}: {self.packet.getTxRxResult(result)}", [servo_id])
        # The alert bit only says a hardware error is latched (read in every state block); any
        # other error number means the instruction was refused.
        if error & 0x7F:
            message = self.packet.getRxPacketError(error & 0x7F)
            raise BusError(f"servo {servo_id}: {what}: {message}", [servo_id])
