"""Dynamixel Protocol 2.0 framing for the emulator: CRC-16, byte stuffing, instruction and status packets.

A packet is `FF FF FD 00 | id | length (2, LE) | instruction | parameters | CRC-16 (2, LE)`, where
length counts instruction, parameters and CRC after stuffing, and any `FF FF FD` inside the
instruction and parameters is followed by a stuffed `FD`. The driver side never uses this module:
it talks through the `dynamixel-sdk` package, so the emulator checks this framing against it.
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = bytes((0xFF, 0xFF, 0xFD, 0x00))
BROADCAST_ID = 0xFE

PING = 0x01
READ = 0x02
WRITE = 0x03
REBOOT = 0x08
STATUS = 0x55
SYNC_READ = 0x82
SYNC_WRITE = 0x83

# Status packet error field: a number in the low 7 bits, the hardware alert in bit 7.
ERR_RESULT_FAIL = 1
ERR_INSTRUCTION = 2
ERR_CRC = 3
ERR_DATA_RANGE = 4
ERR_DATA_LENGTH = 5
ERR_DATA_LIMIT = 6
ERR_ACCESS = 7
ALERT = 0x80


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """Protocol 2.0's CRC-16 (polynomial 0x8005, initial 0, not reflected)."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert `FD` after every `FF FF FD` in instruction and parameters."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if byte == 0xFD and out[-3:-1] == b"\xff\xff":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and out[-3:-1] == b"\xff\xff" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # drop the stuffed FD
        i += 1
    return bytes(out)


def encode(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    body = stuff(bytes((instruction,)) + params)
    head = HEADER + bytes((servo_id,)) + (len(body) + 2).to_bytes(2, "little")
    packet = head + body
    return packet + crc16(packet).to_bytes(2, "little")


def status(servo_id: int, error: int, params: bytes = b"") -> bytes:
    return encode(servo_id, STATUS, bytes((error,)) + params)


@dataclass(frozen=True)
class Packet:
    servo_id: int
    instruction: int
    params: bytes


class BadCrc(ValueError):
    """A packet whose CRC does not match; carries its id so a servo can answer with a CRC error."""

    def __init__(self, servo_id: int) -> None:
        super().__init__(f"CRC mismatch in a packet to id {servo_id}")
        self.servo_id = servo_id


# The length field counts instruction, parameters and CRC: at least an instruction and the CRC.
MIN_LENGTH = 3
# Packets this long or longer are noise: the SDK's own buffers hold 1,024 bytes, header included.
MAX_LENGTH = 1024 - 7


def _whole_packet_at(buffer: bytearray, start: int) -> bool:
    """Whether a whole packet with a sane length and a matching CRC starts at `start`."""
    if len(buffer) < start + 7:
        return False
    length = int.from_bytes(buffer[start + 5 : start + 7], "little")
    end = start + 7 + length
    if not MIN_LENGTH <= length <= MAX_LENGTH or len(buffer) < end:
        return False
    return crc16(buffer[start : end - 2]) == int.from_bytes(buffer[end - 2 : end], "little")


def decode(buffer: bytearray) -> Packet | None:
    """Take the first whole packet off the front of `buffer`, resynchronising past noise.

    Returns None when no whole packet is there yet. A header whose length is out of bounds is
    noise: its first byte is dropped and the scan goes on. So is an unfinished packet when a
    whole, valid packet already starts at a later header (no stuffed packet holds a header), and
    a bad-CRC packet that holds a later header: noise whose length field swallowed real packets
    does not hide them. A bad-CRC packet with no header inside is consumed and raises BadCrc, so
    its servo can answer with a CRC error.
    """
    while True:
        start = buffer.find(HEADER)
        if start < 0:
            del buffer[: max(0, len(buffer) - 3)]  # keep a possible partial header
            return None
        del buffer[:start]
        if len(buffer) < 7:
            return None
        length = int.from_bytes(buffer[5:7], "little")
        if not MIN_LENGTH <= length <= MAX_LENGTH:
            del buffer[:1]
            continue
        end = 7 + length
        later = buffer.find(HEADER, 1, end)
        if len(buffer) < end:
            if later > 0 and _whole_packet_at(buffer, later):
                del buffer[:later]
                continue
            return None
        packet = bytes(buffer[:end])
        if crc16(packet[:-2]) != int.from_bytes(packet[-2:], "little"):
            if later > 0:
                del buffer[:later]
                continue
            del buffer[:end]
            raise BadCrc(packet[4])
        del buffer[:end]
        body = unstuff(packet[7:-2])
        return Packet(packet[4], body[0], body[1:])
