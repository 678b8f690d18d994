"""Frame codec: keyframe + keyframe-relative deltas, each zstd-compressed on its own.

Frames of one episode are grouped in chunks of `chunk_len` consecutive frames.
The first frame of a chunk (the keyframe) is compressed as is; every other
frame is stored as its wrapping uint8 difference to the keyframe. Deltas are
taken to the keyframe rather than to the previous frame so any frame decodes
with at most two decompressions (keyframe + its delta) instead of a chain:
sampling is random access, and decode cost is what limits it. On the six paper
tasks this costs ~10% more bytes than previous-frame deltas at chunk_len 8-16
(measured, see bench/replay.py).
"""

from __future__ import annotations

import numpy as np
import zstandard as zstd


class FrameCodec:
    """Compresses and decompresses single frames; one instance per thread for decompression."""

    def __init__(self, frame_size: int, level: int = 1) -> None:
        self.frame_size = frame_size
        self.level = level
        self._c = zstd.ZstdCompressor(level=level, write_checksum=False)
        self._d = zstd.ZstdDecompressor()

    def encode_key(self, frame: np.ndarray) -> bytes:
        return self._c.compress(frame.tobytes())

    def encode_delta(self, frame: np.ndarray, key: np.ndarray) -> bytes:
        # uint8 subtraction wraps modulo 256, so key + delta restores the frame exactly.
        return self._c.compress(np.subtract(frame, key, dtype=np.uint8).tobytes())

    def decode_into(self, blob: bytes, out: np.ndarray) -> None:
        """Decompress a keyframe into `out` (a contiguous uint8 row of frame_size)."""
        out[:] = np.frombuffer(self._d.decompress(blob, max_output_size=self.frame_size), np.uint8)

    def add_delta_into(self, blob: bytes, key: np.ndarray, out: np.ndarray) -> None:
        """out = key + delta (wrapping); `key` and `out` may not alias."""
        delta = np.frombuffer(self._d.decompress(blob, max_output_size=self.frame_size), np.uint8)
        np.add(key, delta, out=out)

    def decode_key(self, blob: bytes) -> np.ndarray:
        out = np.empty(self.frame_size, np.uint8)
        self.decode_into(blob, out)
        return out
