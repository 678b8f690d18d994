"""Choosing the torch device, with a clear error when CUDA is asked for and absent."""

from __future__ import annotations

import ctypes

import torch

# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
KEEP_FREED_BYTES = 1 << 30


class DeviceError(RuntimeError):
    pass


def resolve_device(name: str) -> torch.device:
    """`auto` -> cuda when present, else cpu; `cuda[:N]` must exist. On the CPU the
    process also keeps freed memory for reuse (`keep_freed_memory`)."""
    device = _parse_device(name)
    if device.type == "cpu":
        keep_freed_memory()
    return device


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed blocks of up to 1 GiB instead of unmapping them.

    By default a freed block over 32 MiB (a batch's decoded images, its gradients)
    goes back to the OS, and the next update page-faults it in afresh, zeroed, a
    measurable part of a CPU update. The process keeps its peak footprint instead.
    A no-op (False) where the C library is not glibc."""
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):
        return False
    kept = mallopt(_M_MMAP_THRESHOLD, KEEP_FREED_BYTES)
    return bool(kept) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES))


def _parse_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise DeviceError(f"unknown device {name!r}: use cpu, cuda, cuda:N or auto") from err
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(
                f"device {name!r} was asked for but CUDA is not available on this machine "
                "(no GPU or a CPU-only torch build); use --device cpu"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise DeviceError(
                f"device {name!r} does not exist: {torch.cuda.device_count()} CUDA device(s)"
            )
    elif device.type != "cpu":
        raise DeviceError(f"unsupported device {name!r}: use cpu, cuda, cuda:N or auto")
    return device
