"""Checkpoints on disk: written atomically, never a pickled object.

A checkpoint is a dict of tensors, numbers, strings and lists saved with
`torch.save` and loaded with `weights_only=True`; it lands by an atomic
rename, so a reader sees the previous checkpoint or the new one, never half
of one.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import random
import signal
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from shared.files import fsync_dir

# 2: the encoder's and decoder's fc layers index conv features in (h, w, c) order.
# 3: one payload for both runners (shared/recorder.py): env_steps, episodes, wall_s, CSV row counts.
CHECKPOINT_FORMAT = 3


class CheckpointError(ValueError):
    """A checkpoint this version cannot continue from (another format, or not a checkpoint)."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_signals_deferred() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) or SIGTERM until the block ends, then deliver it to the handler it
    would have met.

    A KeyboardInterrupt inside torch.save leaves its zip writer half done, which then raises an error
    of its own instead; around a checkpoint, the checkpoint lands first and the interrupt follows.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # signals reach only the main thread
        return
    caught: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for signum in dict.fromkeys(caught):
            signal.raise_signal(signum)


def save(path: str | Path, state: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save({"format": CHECKPOINT_FORMAT, **state}, f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as err:
        tmp.unlink(missing_ok=True)  # a full disk: free what the failed write took; `path` is intact
        # torch's zip writer answers a failed write with an error of its own about file
        # positions: the disk's error is the one to report, naming the file.
        disk = err.__context__ if isinstance(err, RuntimeError) else err
        if isinstance(disk, OSError) and disk.filename is None:
            raise OSError(disk.errno, disk.strerror, str(tmp)) from err
        if disk is not err and isinstance(disk, OSError):
            raise disk from None
        raise
    os.replace(tmp, path)
    fsync_dir(path.parent)  # the rename itself, or a power loss could bring back the older one


def load(path: str | Path, device: torch.device | str = "cpu") -> dict:
    _check_crcs(Path(path))
    try:
        state = torch.load(Path(path), map_location=device, weights_only=True)
    except (RuntimeError, EOFError, pickle.UnpicklingError, UnicodeDecodeError, KeyError, AttributeError,
            ValueError) as err:
        # torch's own text for a foreign or truncated file suggests weights_only=False, which would
        # run whatever the file holds: name the cause in one line instead.
        text = str(err)
        why = ("not a checkpoint this project wrote (truncated, or another kind of file)"
               if not text.strip() or "Weights only load failed" in text else text.splitlines()[0])
        raise CheckpointError(f"{path} is not a readable checkpoint: {why}") from err
    found = state.get("format") if isinstance(state, dict) else None
    if found != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"checkpoint {path} has format {found!r} and this version reads format {CHECKPOINT_FORMAT}: "
            "it cannot be continued; start the run again in a new folder"
        )
    return state


def _check_crcs(path: Path) -> None:
    """torch writes a CRC-32 for each record of its zip file and does not check them on load: a
    damaged byte in a tensor would load as a wrong weight. Checked here first."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as err:
        raise CheckpointError(f"{path} is not a readable checkpoint: {err}") from err
    if bad is not None:
        raise CheckpointError(f"{path} is damaged: its record {bad} fails its checksum; it cannot be "
                              "continued (an older copy, or start the run again in a new folder)")


def rng_state(rng: np.random.Generator) -> dict:
    """Every random state a run draws from: numpy's generator, torch CPU and CUDA, Python's."""
    state = {
        "numpy": _encode_numpy_state(rng.bit_generator.state),
        "torch": torch.get_rng_state(),
        "python": list(random.getstate()[1]),
        "python_version": random.getstate()[0],
        "python_gauss": random.getstate()[2],
    }
    # A run that never touched CUDA has drawn nothing there, and reading the states would open a
    # CUDA context (GPU memory; an error on a GPU held exclusively by another process).
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(rng: np.random.Generator, state: dict) -> None:
    """The random states of `rng_state`, from a checkpoint loaded onto any device: torch takes a
    generator's state only as a CPU tensor, and `load` maps the checkpoint's tensors, these too,
    to the run's device. CUDA states go back to the devices this machine has."""
    rng.bit_generator.state = _decode_numpy_state(state["numpy"])
    torch.set_rng_state(state["torch"].cpu())
    random.setstate((state["python_version"], tuple(state["python"]), state["python_gauss"]))
    if "cuda" in state and torch.cuda.is_available():
        for device, cuda_state in zip(range(torch.cuda.device_count()), state["cuda"], strict=False):
            torch.cuda.set_rng_state(cuda_state.cpu(), device)


def _encode_numpy_state(state: dict) -> dict:
    # PCG64 states are Python ints wider than 64 bits: keep them as decimal strings.
    inner = {k: str(v) for k, v in state["state"].items()}
    return {**state, "state": inner}


def _decode_numpy_state(state: dict) -> dict:
    inner = {k: int(v) for k, v in state["state"].items()}
    return {**state, "state": inner}
