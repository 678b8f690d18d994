"""bench.replay's decode bound decodes exactly the frames a batch of windows holds."""

from __future__ import annotations

import numpy as np
import pytest

from bench.replay import DecodeBound


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_decode_bound_decodes_each_window_frames(compression):
    rng = np.random.default_rng(0)
    episodes = [[rng.integers(0, 256, (3, 12, 12), dtype=np.uint8) for _ in range(n)] for n in (20, 13)]
    bound = DecodeBound(episodes, frame_stack=3, chunk_len=8, compression=compression)
    assert len(bound.windows) == (20 - 3) + (13 - 3)
    sel = rng.integers(0, len(bound.windows), 16)
    out = np.empty((16 * 4, 3 * 12 * 12), np.uint8)
    bound.decode_batch(sel, out)
    np.testing.assert_array_equal(out, bound.raw[bound.rows[sel].reshape(-1)])
    # A window is k+1 consecutive frames of one episode.
    first = np.concatenate([ep[:4] for ep in episodes[:1]]).reshape(4, -1)
    np.testing.assert_array_equal(bound.raw[bound.rows[0]], first)


def test_decode_bound_rates_are_positive():
    rng = np.random.default_rng(1)
    episodes = [[rng.integers(0, 256, (3, 12, 12), dtype=np.uint8) for _ in range(30)]]
    rates = DecodeBound(episodes, 3, 8, "lz4").rates(batch=8, seconds=0.02, plans=4)
    assert set(rates) == {"decode", "decode_cpu", "memcpy", "memcpy_cpu"}
    assert all(v > 0 for v in rates.values())
