"""SSIM on the CPU as one compiled pass per image plane (numba).

The same statistic as `intrinsic.ssim_torch` (scikit-image's defaults), but each
image plane streams through cache-sized buffers and the formula runs fused,
instead of a dozen full-size intermediates (`bench.learner` times it). Per
input row: the horizontal 7-sums of x, y, x^2 + y^2 (SSIM needs only
var_x + var_y) and xy go into a ring of the last seven rows, and the vertical
window slides by adding the new row's sums and dropping the oldest. Rows are
padded to whole vectors; a mask drops the padding.
"""

from __future__ import annotations

import threading

import numba
import numpy as np

WIN = 7
_LANES = 16  # float32 lanes of an AVX-512 vector: rows are padded to a multiple
# Reassociation lets LLVM vectorise the sums; the no-NaN/no-Inf assumptions of full
# fastmath are left out (no faster here). error_model="numpy": a division by zero
# gives inf/NaN as in numpy and torch instead of raising.
_FASTMATH = {"reassoc", "contract", "arcp", "nsz"}
_JIT = dict(fastmath=_FASTMATH, boundscheck=False, error_model="numpy", cache=True)


@numba.njit(**_JIT)
def _plane_ssim_sum(x, y, scale, c1, c2, row, ring, window, valid):
    """Sum of the valid SSIM map of one (H, W) plane pair; x is multiplied by `scale`."""
    height, width = x.shape
    span = window.shape[1]
    n = WIN * WIN
    cov_norm = np.float32(n / (n - 1.0))  # sample covariance
    inv_n = np.float32(1.0 / n)
    ring[:] = 0.0
    window[:] = 0.0
    total = 0.0
    for h in range(height):
        # Three loops, so that the products vectorise even when y is strided.
        for w in range(width):
            row[0, w] = np.float32(x[h, w]) * scale
        for w in range(width):
            row[1, w] = y[h, w]
        for w in range(width):
            a = row[0, w]
            b = row[1, w]
            row[2, w] = a * a + b * b
            row[3, w] = a * b
        slot = h % WIN
        for q in range(4):
            for j in range(span):
                s = (
                    row[q, j] + row[q, j + 1] + row[q, j + 2] + row[q, j + 3]
                    + row[q, j + 4] + row[q, j + 5] + row[q, j + 6]
                )
                window[q, j] += s - ring[slot, q, j]
                ring[slot, q, j] = s
        if h >= WIN - 1:
            acc = np.float32(0.0)
            for j in range(span):
                ux = window[0, j] * inv_n
                uy = window[1, j] * inv_n
                uxuy = ux * uy
                u2 = ux * ux + uy * uy
                numerator = (2 * uxuy + c1) * (2 * cov_norm * (window[3, j] * inv_n - uxuy) + c2)
                denominator = (u2 + c1) * (cov_norm * (window[2, j] * inv_n - u2) + c2)
                acc += valid[j] * (numerator / denominator)
            total += acc
    return total


@numba.njit(parallel=True, **_JIT)
def _batch_ssim(x, y, scale):
    batch, channels, height, width = x.shape
    cols = width - WIN + 1
    span = (cols + _LANES - 1) // _LANES * _LANES
    valid = np.zeros(span, np.float32)
    valid[:cols] = 1.0
    out = np.empty(batch, np.float64)
    scale = np.float32(scale)
    for b in numba.prange(batch):
        row = np.zeros((4, span + WIN - 1), np.float32)  # zero padding past the image
        ring = np.empty((WIN, 4, span), np.float32)
        window = np.empty((4, span), np.float32)
        pixels = x[b].ravel()  # one flat loop: the min/max reduction vectorises
        lo = pixels[0]
        hi = lo
        for i in range(pixels.size):
            lo = min(lo, pixels[i])
            hi = max(hi, pixels[i])
        data_range = (np.float32(hi) - np.float32(lo)) * scale
        c1 = (np.float32(0.01) * data_range) ** 2
        c2 = (np.float32(0.03) * data_range) ** 2
        total = 0.0
        for c in range(channels):
            total += _plane_ssim_sum(x[b, c], y[b, c], scale, c1, c2, row, ring, window, valid)
        out[b] = total / (channels * (height - WIN + 1) * cols)
    return out


# numba's plain thread pool (workqueue) must not be entered from two threads at once.
_lock = threading.Lock()


def batch_ssim(x: np.ndarray, y: np.ndarray, x_scale: float, threads: int) -> np.ndarray:
    """Mean SSIM per sample of (B, C, H, W) arrays of any strides: x * x_scale and y in [0, 1]."""
    x = np.ascontiguousarray(x)
    with _lock:
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        return _batch_ssim(x, y, x_scale)
