"""Durability files of a replay data directory: manifest, append-only log segments, snapshots.

Layout of a data directory:

    MANIFEST.json          format name, version and the store's shape config
    log-000003.bin         append-only records of every mutation since snapshot 3
    snapshot-000003.bin    compacted state as of the start of log segment 3

A log record is `<u32 payload length><u32 crc32(type + payload)><u8 type>` then
the payload. Records are written with one `os.write` on an O_APPEND descriptor,
so once the call returns the bytes are in the OS page cache and survive the
death of the process (kill -9); `fsync` (power loss) is periodic and on flush.
A torn or corrupt record at the end of the newest segment, with no intact record
after it, is the half-written tail of a crash: it is cut off at reopen. Damage
anywhere else is an error, and nothing is cut.

A snapshot is a list of named, crc-checked sections ending with a `DONE`
section, written to a temporary name, fsynced and renamed: a snapshot without
DONE is never read.
"""

from __future__ import annotations

import errno
import json
import os
import re
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

from shared.files import fsync_dir, replace_text

FORMAT_NAME = "nasa-td3-replay"
FORMAT_VERSION = 2  # 2: the manifest names the frame compressor (lz4 or zstd); 1 was zstd only
MANIFEST = "MANIFEST.json"
_HEADER = struct.Struct("<IIB")
_SEG_RE = re.compile(r"^log-(\d{6})\.bin$")
_SNAP_RE = re.compile(r"^snapshot-(\d{6})\.bin$")
_SNAP_MAGIC = b"NASARPS1"
_MAX_RECORD = 1 << 30


class StoreFormatError(RuntimeError):
    """A data directory that this code cannot read (other version, other config, corruption)."""


def write_manifest(data_dir: Path, config: dict) -> None:
    body = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": config}
    replace_text(data_dir / MANIFEST, json.dumps(body, indent=1, sort_keys=True), durable=True)


def check_manifest(data_dir: Path, config: dict) -> bool:
    """True if the directory holds a store of this version and config; False if it holds none."""
    path = data_dir / MANIFEST
    if not path.exists():
        if any(_SEG_RE.match(p.name) or _SNAP_RE.match(p.name) for p in data_dir.iterdir()):
            raise StoreFormatError(f"{data_dir} has replay log files but no {MANIFEST}")
        return False
    try:
        body = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise StoreFormatError(f"{path} is unreadable: {e}") from e
    if body.get("format") != FORMAT_NAME:
        raise StoreFormatError(f"{data_dir} is not a replay store (format {body.get('format')!r})")
    if body.get("version") != FORMAT_VERSION:
        raise StoreFormatError(
            f"{data_dir} holds replay format version {body.get('version')}, this code reads "
            f"version {FORMAT_VERSION}; use a new data_dir or convert the old one"
        )
    stored = body.get("config")
    if isinstance(stored, dict) and stored.get("prioritized") is False:
        # Written before prioritized sampling was removed: the same format, always uniform.
        stored = {k: v for k, v in stored.items() if k != "prioritized"}
    if stored != config:
        raise StoreFormatError(
            f"{data_dir} was created with config {stored}, "
            f"which differs from the requested {config}"
        )
    return True


def list_numbered(data_dir: Path) -> tuple[list[int], list[int]]:
    """(log segment numbers, snapshot numbers), ascending."""
    segs, snaps = [], []
    for p in data_dir.iterdir():
        if m := _SEG_RE.match(p.name):
            segs.append(int(m.group(1)))
        elif m := _SNAP_RE.match(p.name):
            snaps.append(int(m.group(1)))
    return sorted(segs), sorted(snaps)


def segment_path(data_dir: Path, n: int) -> Path:
    return data_dir / f"log-{n:06d}.bin"


def snapshot_path(data_dir: Path, n: int) -> Path:
    return data_dir / f"snapshot-{n:06d}.bin"


def _record_crc(rtype: int, payload: bytes | memoryview) -> int:
    """A log record's checksum: crc32 of its type byte and its payload."""
    return zlib.crc32(payload, zlib.crc32(bytes([rtype])))


class LogWriter:
    """Appends records to one segment file; `append` returns once the OS has the bytes."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self.bytes_written = os.fstat(self._fd).st_size
        self.dirty = False

    def append(self, rtype: int, payload: bytes) -> None:
        crc = _record_crc(rtype, payload)
        data = _HEADER.pack(len(payload), crc, rtype) + payload
        try:
            n = os.write(self._fd, data)
            if n != len(data):  # a short write on a regular file means the disk is full
                raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} (a short write, {n} of "
                              f"{len(data)} bytes)", str(self.path))
        except OSError as err:
            # Cut what part of the record was written: the log never holds a torn record in its
            # middle, and the caller may append again once there is space.
            os.ftruncate(self._fd, self.bytes_written)
            if err.filename is None:  # os.write names no file: name the log it failed to grow
                raise OSError(err.errno, err.strerror, str(self.path)) from err
            raise
        self.bytes_written += n
        self.dirty = True

    def cut(self, size: int) -> None:
        """Drop what was appended after the log was `size` bytes long."""
        os.ftruncate(self._fd, size)
        self.bytes_written = size

    def sync(self) -> None:
        if self.dirty:
            os.fsync(self._fd)
            self.dirty = False

    def close(self) -> None:
        if self._fd >= 0:
            self.sync()
            os.close(self._fd)
            self._fd = -1


def read_segment(path: Path, is_last: bool) -> Iterator[tuple[int, memoryview]]:
    """Yield (type, payload) of each record; cut a torn tail off the last segment."""
    data = memoryview(path.read_bytes())
    pos = 0
    while pos < len(data):
        bad = None
        if pos + _HEADER.size > len(data):
            bad = "truncated header"
        else:
            length, crc, rtype = _HEADER.unpack_from(data, pos)
            end = pos + _HEADER.size + length
            if length > _MAX_RECORD or end > len(data):
                bad = "truncated record"
            else:
                payload = data[pos + _HEADER.size : end]
                if _record_crc(rtype, payload) != crc:
                    bad = "checksum mismatch"
        if bad is not None:
            if not is_last:
                raise StoreFormatError(f"{path} is corrupt at byte {pos} ({bad})")
            if (after := _next_record(data, pos + 1)) is not None:
                raise StoreFormatError(
                    f"{path} is corrupt at byte {pos} ({bad}), and an intact record follows at byte "
                    f"{after}: damage, not the torn tail of a crash, so nothing was cut. To go on "
                    f"without the records from byte {pos}: truncate -s {pos} {path}")
            # The half-written tail of a crashed writer: nothing in it was acknowledged.
            with open(path, "r+b") as f:
                f.truncate(pos)
                os.fsync(f.fileno())
            return
        yield rtype, payload
        pos = end


def _next_record(data: memoryview, start: int) -> int | None:
    """The offset of the first intact record (its checksum holds) at or after `start`, or None."""
    for pos in range(start, len(data) - _HEADER.size + 1):
        length, crc, rtype = _HEADER.unpack_from(data, pos)
        end = pos + _HEADER.size + length
        if end <= len(data) and _record_crc(rtype, data[pos + _HEADER.size : end]) == crc:
            return pos
    return None


def write_snapshot(path: Path, sections: list[tuple[str, bytes | memoryview]]) -> int:
    """Write sections + DONE to a temp file, fsync, rename. Returns bytes written."""
    tmp = path.with_suffix(".tmp")
    total = 0
    try:
        with open(tmp, "wb") as f:
            f.write(_SNAP_MAGIC)
            for name, data in [*sections, ("DONE", b"")]:
                nb = name.encode()
                f.write(struct.pack("<H", len(nb)) + nb)
                f.write(struct.pack("<QI", len(data), zlib.crc32(data)))
                f.write(data)
                total += len(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a half-written snapshot would hold disk the log needs
        raise
    fsync_dir(path.parent)
    return total


def read_snapshot(path: Path) -> dict[str, memoryview]:
    data = memoryview(path.read_bytes())
    if bytes(data[:8]) != _SNAP_MAGIC:
        raise StoreFormatError(f"{path} is not a replay snapshot")
    pos, out = 8, {}
    while True:
        try:
            (nlen,) = struct.unpack_from("<H", data, pos)
            name = bytes(data[pos + 2 : pos + 2 + nlen]).decode()
            pos += 2 + nlen
            length, crc = struct.unpack_from("<QI", data, pos)
            pos += 12
        except struct.error as e:
            raise StoreFormatError(f"{path} is truncated (no DONE section)") from e
        body = data[pos : pos + length]
        if len(body) != length or zlib.crc32(body) != crc:
            raise StoreFormatError(f"{path} section {name!r} is corrupt")
        pos += length
        if name == "DONE":
            return out
        out[name] = body
