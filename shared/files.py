"""File-system helpers shared by the run's writers: whole-file replacement, folder fsync, log tails,
and values made fit for strict JSON."""

from __future__ import annotations

import math
import os
from pathlib import Path


def fsync_dir(path: str | Path) -> None:
    """fsync a folder, so the names created, renamed or removed in it survive a power loss (an
    fsynced file that was renamed into place is not enough)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_text(path: str | Path, text: str, tmp: str | Path | None = None, durable: bool = False) -> None:
    """Write `text` to `path` whole or not at all: into `tmp` (default: `path` + ".tmp"), then
    renamed over `path`, so a reader sees the old file or the new one, never half of one. A write
    that fails (a full disk) removes the temporary copy, freeing what it took; `path` stays as it
    was. `durable`: the text and the rename are fsynced, so they survive a power loss too."""
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if tmp.is_file():
            tmp.unlink()
        raise
    if durable:
        fsync_dir(path.parent)


def last_line(path: str | Path, max_bytes: int = 4096) -> str:
    """The last non-blank line of a text file, "" for none, read from its end only (a log may be
    large). Progress bars' carriage returns end lines too. OSError where it cannot be read."""
    with open(path, "rb") as f:
        f.seek(max(0, f.seek(0, os.SEEK_END) - max_bytes))
        lines = f.read().decode("utf-8", "replace").splitlines()
    return next((line.strip() for line in reversed(lines) if line.strip()), "")


def finite_only(value: object) -> object:
    """`value` with each NaN or infinite float, which JSON has no word for, as None (null)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_only(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_only(v) for v in value]
    return value
