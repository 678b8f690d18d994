"""File-system durability shared by the replay's log and the checkpoints."""

from __future__ import annotations

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
