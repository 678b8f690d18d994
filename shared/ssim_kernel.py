"""SSIM on the CPU as one compiled pass per image plane (numba).

The same statistic as `intrinsic.ssim_torch` (scikit-image's defaults), but each
image plane streams through cache-sized buffers and the formula runs fused,
instead of a dozen full-size intermediates (`bench.learner` times it). Per
input row: the horizontal 7-sums of x, y, x^2 + y^2 (SSIM needs only
var_x + var_y) and xy go into a ring of the last seven rows, and the vertical
window slides by adding the new row's sums and dropping the oldest. Rows are
padded to whole vectors; a mask drops the padding.

y may also be a decoder's logits, float32 or bfloat16 (as its raw bits in int16),
with the sigmoid applied as each row is read: that spares the full-size float32
copy and the sigmoid's pass over it. The sigmoid's exp is computed here in a form
the compiler vectorises (numba's own `exp` is a scalar library call).
"""

from __future__ import annotations

import os
import threading

import numba
import numpy as np

# numba's `omp` threading layer loads the system's libgomp, a second OpenMP runtime beside torch's,
# which reads the same OMP_WAIT_POLICY: under ACTIVE (`nasa up`'s learner on a small machine) its
# worker, once started by a two-thread SSIM, spins for the rest of the process on a core the
# learner's own threads need. There the plain pool, which sleeps between calls, is used; elsewhere
# numba's own choice stays, the faster where it is `omp`. A layer the user names is kept.
if "NUMBA_THREADING_LAYER" not in os.environ and os.environ.get("OMP_WAIT_POLICY", "").upper() == "ACTIVE":
    numba.config.THREADING_LAYER = "workqueue"

WIN = 7
RANGE_FLOOR = 0.2
"""The least data range SSIM takes (images in [0, 1]). The reference takes max - min of the
observation, which is 0 for a uniform stack (black, grey, an overexposed camera): both SSIM
constants vanish and the score is 0/0 plus rounding. Just above 0 it is still rounding, as the
constants fall below float32's error in the window variances, so the floor sits where they
dominate it. Observations whose range is at least the floor score as in the reference."""
_LANES = 16  # float32 lanes of an AVX-512 vector: rows are padded to a multiple
# Reassociation lets LLVM vectorise the sums; the no-NaN/no-Inf assumptions of full
# fastmath are left out (no faster here). error_model="numpy": a division by zero
# gives inf/NaN as in numpy and torch instead of raising.
_FASTMATH = {"reassoc", "contract", "arcp", "nsz"}
_JIT = dict(fastmath=_FASTMATH, boundscheck=False, error_model="numpy", cache=True)


# exp(v) = 2^k e^r, k = round(v / ln 2), |r| <= ln(2) / 2, e^r by Cephes' expf polynomial
# (relative error about 1e-7). ln 2 is split in two so that k ln 2 is exact enough.
_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EXP_MAX = np.float32(87.0)  # e^87 is finite in float32, and 2^126 a normal number
_P0, _P1, _P2 = np.float32(1.9875691500e-4), np.float32(1.3981999507e-3), np.float32(8.3334519073e-3)
_P3, _P4, _P5 = np.float32(4.1665795894e-2), np.float32(1.6666665459e-1), np.float32(5.0000001201e-1)


@numba.njit(**_JIT)
def _read_row(y, h, width, bf16, logits, out, bits, exps):
    """Row h of y into out[:width] as float32: y's bfloat16 bits widened (`bf16`), and
    through the sigmoid (`logits`). `bits` is an int32 buffer and `exps` its float32 view."""
    if bf16:
        for w in range(width):
            bits[w] = np.int32(y[h, w]) << 16  # a bfloat16 is a float32's upper half
        for w in range(width):
            out[w] = exps[w]
    else:
        for w in range(width):
            out[w] = y[h, w]
    if not logits:
        return
    # sigmoid(v) = 1 / (1 + e^-v); a NaN stays NaN (every comparison with it is false).
    for w in range(width):
        v = -out[w]
        if v > _EXP_MAX:
            v = _EXP_MAX
        if v < -_EXP_MAX:
            v = -_EXP_MAX
        k = np.floor(v * _LOG2E + np.float32(0.5))
        r = v - k * _LN2_HI - k * _LN2_LO
        p = (((((_P0 * r + _P1) * r + _P2) * r + _P3) * r + _P4) * r + _P5) * r * r + r + np.float32(1.0)
        bits[w] = (np.int32(k) + 127) << 23  # 2^k
        out[w] = p
    for w in range(width):
        out[w] = np.float32(1.0) / (np.float32(1.0) + out[w] * exps[w])


@numba.njit(**_JIT)
def _plane_ssim_sum(x, y, scale, c1, c2, row, ring, window, valid, bf16, logits, bits, exps):
    """Sum of the valid SSIM map of one (H, W) plane pair; x is multiplied by `scale`, and y
    read by `_read_row`."""
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
        _read_row(y, h, width, bf16, logits, row[1], bits, exps)
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
def _batch_ssim(x, y, scale, range_floor, bf16, logits):
    batch, channels, height, width = x.shape
    cols = width - WIN + 1
    span = (cols + _LANES - 1) // _LANES * _LANES
    valid = np.zeros(span, np.float32)
    valid[:cols] = 1.0
    out = np.empty(batch, np.float64)
    scale = np.float32(scale)
    range_floor = np.float32(range_floor)
    for b in numba.prange(batch):
        row = np.zeros((4, span + WIN - 1), np.float32)  # zero padding past the image
        ring = np.empty((WIN, 4, span), np.float32)
        window = np.empty((4, span), np.float32)
        bits = np.empty(width, np.int32)
        exps = bits.view(np.float32)
        pixels = x[b].ravel()  # one flat loop: the min/max reduction vectorises
        lo = pixels[0]
        hi = lo
        for i in range(pixels.size):
            lo = min(lo, pixels[i])
            hi = max(hi, pixels[i])
        data_range = max((np.float32(hi) - np.float32(lo)) * scale, range_floor)
        c1 = (np.float32(0.01) * data_range) ** 2
        c2 = (np.float32(0.03) * data_range) ** 2
        total = 0.0
        for c in range(channels):
            total += _plane_ssim_sum(
                x[b, c], y[b, c], scale, c1, c2, row, ring, window, valid, bf16, logits, bits, exps
            )
        out[b] = total / (channels * (height - WIN + 1) * cols)
    return out


# numba's plain thread pool (workqueue) must not be entered from two threads at once.
_lock = threading.Lock()


def batch_ssim(
    x: np.ndarray, y: np.ndarray, x_scale: float, threads: int, y_bf16: bool = False, y_logits: bool = False,
    range_floor: float = RANGE_FLOOR,
) -> np.ndarray:
    """Mean SSIM per sample of (B, C, H, W) arrays of any strides: x * x_scale and y in [0, 1].

    `y_bf16`: y is int16, the bits of bfloat16 values. `y_logits`: y holds logits, and the
    SSIM is taken with their sigmoid. `range_floor`: the least data range (0: the reference's)."""
    x = np.ascontiguousarray(x)
    with _lock:
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        return _batch_ssim(x, y, x_scale, range_floor, y_bf16, y_logits)
