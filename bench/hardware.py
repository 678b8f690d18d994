"""The hardware anchor of the benchmarks: what this machine can do at best, measured in the same run.

- `machine()`: CPU model, cores, torch threads, GPU name (for the record beside the figures).
- `matmul_peak_gflops`: the best GFLOP/s of large square `torch.mm` in one dtype on one device
  (fp32 sgemm on the CPU with the threads torch uses; TF32 or BF16 on a GPU).
- `count_flops`: the floating-point operations of a call, by torch's FLOP counter (matmuls and
  convolutions, forward and backward; elementwise ops and kernels outside torch count zero).
- `PartMeter`: wall time and FLOPs of named methods of an object while another call runs
  (the parts of an update: critic, autoencoder, actor, ensemble).
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch.utils.flop_counter import FlopCounterMode


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (the platform's processor string elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine(device: torch.device | None = None) -> dict:
    info = {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
    }
    if device is not None and device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@contextmanager
def matmul_precision(dtype: torch.dtype, tf32: bool) -> Iterator[None]:
    """TF32 on or off for fp32 CUDA matmuls, restored afterwards."""
    before = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = tf32 and dtype == torch.float32
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = before


def matmul_peak_gflops(
    device: torch.device,
    dtype: torch.dtype = torch.float32,
    sizes: tuple[int, ...] = (1024, 2048),
    seconds: float = 1.0,
    tf32: bool = False,
) -> float:
    """The best GFLOP/s of n x n @ n x n over `sizes` and the device's GEMM libraries (`gemm_calls`),
    each timed for about `seconds` after one untimed call. 2 n^3 FLOPs per product (n^3
    multiply-adds)."""
    best = 0.0
    gen = torch.Generator(device="cpu").manual_seed(0)
    with matmul_precision(dtype, tf32):
        for n in sizes:
            a = torch.randn(n, n, generator=gen).to(device=device, dtype=dtype)
            b = torch.randn(n, n, generator=gen).to(device=device, dtype=dtype)
            for product in gemm_calls(a, b).values():
                product()
                sync(device)
                calls, start = 0, time.perf_counter()
                while True:
                    product()
                    calls += 1
                    if calls % 4 == 0 or device.type == "cpu":
                        sync(device)
                        elapsed = time.perf_counter() - start
                        if elapsed >= seconds and calls >= 2:
                            break
                best = max(best, 2.0 * n**3 * calls / elapsed / 1e9)
    return best


def gemm_calls(a: torch.Tensor, b: torch.Tensor) -> dict[str, Callable[[], torch.Tensor]]:
    """Ways this device computes a @ b. On a CPU, torch.mm (BLAS: MKL, which on some CPUs takes
    a slower path than the hardware allows) and the same product as a 1x1 convolution through
    oneDNN, which the update's convolutions use: the peak is the faster of the two."""
    out = torch.empty(a.shape[0], b.shape[1], device=a.device, dtype=a.dtype)
    calls: dict[str, Callable[[], torch.Tensor]] = {"mm": lambda: torch.mm(a, b, out=out)}
    if a.device.type == "cpu":
        # Channels-last (1, k, m, 1) input and (n, k, 1, 1) weight: out[0, :, i, 0] = a[i] @ b.
        x = a.t().reshape(1, a.shape[1], a.shape[0], 1).contiguous(memory_format=torch.channels_last)
        w = b.t().reshape(b.shape[1], b.shape[0], 1, 1).contiguous(memory_format=torch.channels_last)

        def conv() -> torch.Tensor:
            with torch.no_grad():
                return torch.nn.functional.conv2d(x, w)

        calls["onednn_conv1x1"] = conv
    return calls


def count_flops(fn: Callable[[], object]) -> int:
    """FLOPs of fn() as torch's FLOP counter sees them (one multiply-add = 2)."""
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return int(counter.get_total_flops())


class PartMeter:
    """Wall time and (when counting) FLOPs spent in named methods of `obj`.

    `parts` maps a part's name to the method names that make it up; a method
    `obj` lacks is left out (the part then holds the others, or is absent).
    Inside `with meter.attached():` each call to such a method adds its
    duration (device synchronised before and after) to its part; with
    `count=True` each also runs under its own FLOP counter. Methods called
    from inside another metered method are counted once, in the outer part.
    """

    def __init__(self, obj: object, parts: dict[str, tuple[str, ...]], device: torch.device) -> None:
        self.obj, self.device = obj, device
        self.parts = {
            name: tuple(m for m in methods if callable(getattr(obj, m, None)))
            for name, methods in parts.items()
        }
        self.parts = {name: methods for name, methods in self.parts.items() if methods}
        self.seconds = dict.fromkeys(self.parts, 0.0)
        self.flops = dict.fromkeys(self.parts, 0)
        self._depth = 0

    def reset(self) -> None:
        self.seconds = dict.fromkeys(self.parts, 0.0)
        self.flops = dict.fromkeys(self.parts, 0)

    @contextmanager
    def attached(self, count: bool = False) -> Iterator[PartMeter]:
        originals, own = {}, dict(vars(self.obj))
        for part, methods in self.parts.items():
            for method in methods:
                originals[method] = getattr(self.obj, method)
                setattr(self.obj, method, self._wrap(part, originals[method], count))
        try:
            yield self
        finally:
            for method in originals:
                if method in own:
                    setattr(self.obj, method, own[method])
                else:
                    delattr(self.obj, method)  # the class's method shows through again

    def _wrap(self, part: str, fn: Callable, count: bool) -> Callable:
        def metered(*args, **kwargs):
            if self._depth:
                return fn(*args, **kwargs)
            self._depth += 1
            try:
                sync(self.device)
                start = time.perf_counter()
                if count:
                    counter = FlopCounterMode(display=False)
                    with counter:
                        result = fn(*args, **kwargs)
                    self.flops[part] += int(counter.get_total_flops())
                else:
                    result = fn(*args, **kwargs)
                sync(self.device)
                self.seconds[part] += time.perf_counter() - start
                return result
            finally:
                self._depth -= 1

        return metered
