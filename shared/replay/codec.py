"""Frame codec: keyframe + keyframe-relative deltas, each compressed on its own.

Frames of one episode are grouped in chunks of `chunk_len` consecutive frames.
The first frame of a chunk (the keyframe) is compressed as is; every other
frame is stored as its wrapping uint8 difference to the keyframe. Deltas are
taken to the keyframe rather than to the previous frame so any frame decodes
with at most two decompressions (keyframe + its delta) instead of a chain:
sampling is random access, and decode cost is what limits it. The price is a
few percent more bytes than previous-frame deltas (docs/benchmarks.md).

Two compressors (`compression`):
- "lz4" (default), LZ4 HC at level 4: decompresses several times faster than
  zstd, for somewhat more bytes;
- "zstd" at level 1: the smallest store, slower to sample.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import lz4.block
import numpy as np
import zstandard as zstd

COMPRESSIONS = ("lz4", "zstd")
DEFAULT_LEVEL = {"lz4": 4, "zstd": 1}


class FrameCodec:
    """Compresses and decompresses single frames; one instance per thread for decompression."""

    def __init__(self, frame_size: int, compression: str = "lz4") -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"unknown compression {compression!r}; choose one of {COMPRESSIONS}")
        self.frame_size = frame_size
        self.compression = compression
        self.level = DEFAULT_LEVEL[compression]
        # decompress(blob) -> bytes of frame_size; a partial of a C function, no Python frame
        # in between: sampling calls it about 5 times per transition.
        self.decompress: Callable[[bytes], bytes]
        if compression == "zstd":
            self._compress = zstd.ZstdCompressor(level=self.level, write_checksum=False).compress
            self.decompress = partial(zstd.ZstdDecompressor().decompress, max_output_size=frame_size)
        else:
            self._compress = partial(
                lz4.block.compress, mode="high_compression", compression=self.level, store_size=False
            )
            self.decompress = partial(lz4.block.decompress, uncompressed_size=frame_size)

    def encode_key(self, frame: np.ndarray) -> bytes:
        return self._compress(frame.tobytes())

    def encode_delta(self, frame: np.ndarray, key: np.ndarray) -> bytes:
        # uint8 subtraction wraps modulo 256, so key + delta restores the frame exactly.
        return self._compress(np.subtract(frame, key, dtype=np.uint8).tobytes())

    def decode(self, blob: bytes) -> np.ndarray:
        """A keyframe, or a delta to add to its keyframe: a read-only uint8 row of frame_size."""
        return np.frombuffer(self.decompress(blob), np.uint8)
