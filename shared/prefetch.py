"""A device prefetcher: sampling, decompression and the host-to-device copy overlap the update.

A thread calls `sample()` (a replay client's sample: decompressed numpy arrays),
copies the arrays the update needs into a staging slot and starts their copy to
the device; the learner takes finished batches from a bounded queue with `get()`.

On CUDA the staging slots are pinned host buffers and the copies are
non-blocking on a side stream: the learner's stream waits on each batch's event
only when it takes the batch, and each device tensor is marked as used by the
learner's stream so the caching allocator never hands its memory back early. A
slot is refilled only after its previous copy finished (its event). On the CPU
the same code runs with plain staging buffers and no streams, which is what the
unit tests exercise; there the thread still overlaps sampling with the update.

The frames travel once: when the batch holds `window` (each transition's k+1
frames, of which `obs` and `next_obs` are views), only the window is copied and
`obs` / `next_obs` are device views of it.

`intrinsic` is copied as sampled: rows still unscored (NaN) must be scored and
patched on the device by the consumer before the update reads them.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

Batch = dict[str, np.ndarray]
DEVICE_KEYS = ("obs", "next_obs", "action", "reward", "discount", "intrinsic")


@dataclass
class Prefetched:
    """A batch on the device (`device`) and the sampled host arrays it came from (`host`:
    index, policy_version and the rest, for the learner's bookkeeping)."""

    host: Batch
    device: dict[str, torch.Tensor]


class PrefetchError(RuntimeError):
    """The sampling thread failed; the original error is the cause."""


class _Staging:
    """Host buffers for one batch in flight, pinned on CUDA, and the event of their last copy."""

    def __init__(self, pin: bool) -> None:
        self.pin = pin
        self.buffers: dict[str, torch.Tensor] = {}
        self.event: torch.cuda.Event | None = None

    def fill(self, arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """Copy the arrays into this slot's buffers (made, or remade when a shape changes)."""
        if self.event is not None:
            self.event.synchronize()  # the previous copy out of these buffers has finished
        for key, array in arrays.items():
            buf = self.buffers.get(key)
            if buf is None or tuple(buf.shape) != array.shape or buf.numpy().dtype != array.dtype:
                buf = torch.empty(array.shape, dtype=torch.from_numpy(array[:0]).dtype, pin_memory=self.pin)
                self.buffers[key] = buf
            np.copyto(buf.numpy(), array, casting="no")
        return {key: self.buffers[key] for key in arrays}


def transfer_keys(batch: Batch, keys: tuple[str, ...]) -> tuple[str, ...]:
    """The arrays to copy: `window` in place of obs and next_obs when the batch has it."""
    if "window" in batch and "obs" in keys and "next_obs" in keys:
        return ("window", *[k for k in keys if k not in ("obs", "next_obs")])
    return tuple(keys)


def frame_views(device_batch: dict[str, torch.Tensor], obs_channels: int) -> None:
    """obs and next_obs as views of the copied window: its first and last `obs_channels` channels."""
    window = device_batch.pop("window")
    frame_channels = window.shape[1] - obs_channels
    device_batch["obs"] = window[:, :obs_channels]
    device_batch["next_obs"] = window[:, frame_channels:]


class DevicePrefetcher:
    """Keeps up to `depth` batches on the device ahead of the learner.

    `sample()` returns a batch or None (replay not ready: the thread waits `idle_s`
    and asks again). Use as a context manager, or `start()` and `close()`.
    `waited_s` is the time `get()` spent waiting: near zero when the learner
    never waits on the replay.
    """

    def __init__(
        self,
        sample: Callable[[], Batch | None],
        device: torch.device,
        depth: int = 2,
        keys: tuple[str, ...] = DEVICE_KEYS,
        idle_s: float = 0.01,
    ) -> None:
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self.sample, self.device, self.keys, self.idle_s = sample, device, keys, idle_s
        self.cuda = device.type == "cuda"
        self.stream = torch.cuda.Stream(device) if self.cuda else None
        # depth batches may wait in the queue and one more is being staged.
        self._slots = [_Staging(pin=self.cuda) for _ in range(depth + 1)]
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="device-prefetch", daemon=True)
        self.waited_s = 0.0

    def start(self) -> DevicePrefetcher:
        self._thread.start()
        return self

    def __enter__(self) -> DevicePrefetcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def get(self, timeout: float | None = None) -> Prefetched | None:
        """The next batch, ready to use on the current stream; None after `timeout` seconds.
        Raises PrefetchError when the sampling thread failed."""
        start = time.perf_counter()
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            item = None
        self.waited_s += time.perf_counter() - start
        if isinstance(item, BaseException):
            self._queue.put(item)  # every later get() raises too
            raise PrefetchError(f"the prefetch thread failed: {item!r}") from item
        if item is None:
            return None
        host, device_batch, event = item
        if self.cuda:
            current = torch.cuda.current_stream(self.device)
            current.wait_event(event)
            for tensor in device_batch.values():
                tensor.record_stream(current)
        return Prefetched(host, device_batch)

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        while True:  # unblock a producer waiting on a full queue
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        if self._thread.is_alive():
            self._thread.join(timeout)

    # -- the thread ---------------------------------------------------------------

    def _run(self) -> None:
        slot = 0
        try:
            while not self._stop.is_set():
                batch = self.sample()
                if batch is None:
                    self._stop.wait(self.idle_s)
                    continue
                item = self._stage(batch, self._slots[slot])
                slot = (slot + 1) % len(self._slots)
                self._put(item)
        except BaseException as err:  # handed to the consumer, who raises it
            self._put(err)

    def _put(self, item: object) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _stage(self, batch: Batch, staging: _Staging) -> tuple:
        keys = transfer_keys(batch, self.keys)
        host = staging.fill({key: batch[key] for key in keys})
        event = None
        if self.cuda:
            with torch.cuda.stream(self.stream):
                device_batch = {k: t.to(self.device, non_blocking=True) for k, t in host.items()}
                event = torch.cuda.Event()
                event.record(self.stream)
            staging.event = event
        else:
            device_batch = {k: t.to(self.device, copy=True) for k, t in host.items()}
        if "window" in device_batch:
            frame_views(device_batch, batch["obs"].shape[1])
        return batch, device_batch, event
