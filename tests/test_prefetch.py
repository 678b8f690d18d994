"""The device prefetcher on the CPU: order, contents, bounded queue, staging reuse, errors, close."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest
import torch

from shared.prefetch import DevicePrefetcher, PrefetchError, transfer_keys

CPU = torch.device("cpu")


def make_batch(i: int, b: int = 4, k: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(i)
    window = rng.integers(0, 256, (b, 3 * (k + 1), 8, 8), dtype=np.uint8)
    return {
        "window": window,
        "obs": window[:, : 3 * k],
        "next_obs": window[:, 3:],
        "action": rng.uniform(-1, 1, (b, 2)).astype(np.float32),
        "reward": np.full(b, float(i), np.float32),
        "discount": np.ones(b, np.float32),
        "intrinsic": np.full(b, np.nan, np.float32),
        "index": np.arange(b, dtype=np.int64) + 100 * i,
    }


class Sampler:
    def __init__(self, count: int | None = None, none_every: int = 0) -> None:
        self.calls, self.count, self.none_every = 0, count, none_every
        self.made: list[dict] = []
        self.called = threading.Condition()

    def __call__(self):
        with self.called:
            self.calls += 1
            self.called.notify_all()
        if self.none_every and self.calls % self.none_every == 0:
            return None
        batch = make_batch(len(self.made))
        self.made.append(batch)
        return batch

    def wait_calls(self, n: int, timeout: float = 30.0) -> None:
        with self.called:
            assert self.called.wait_for(lambda: self.calls >= n, timeout)


def test_batches_arrive_in_order_with_their_contents():
    sampler = Sampler()
    with DevicePrefetcher(sampler, CPU, depth=2) as prefetch:
        got = [prefetch.get(timeout=30) for _ in range(6)]
    for i, item in enumerate(got):
        want = sampler.made[i]
        assert item.host is want
        for key in ("obs", "next_obs", "action", "reward", "discount"):
            np.testing.assert_array_equal(item.device[key].numpy(), want[key])
        assert torch.isnan(item.device["intrinsic"]).all()
        assert item.device["obs"].dtype == torch.uint8 and item.device["reward"].dtype == torch.float32
        assert "window" not in item.device and "index" not in item.device


def test_frames_travel_once_and_obs_next_obs_are_views_of_one_window():
    with DevicePrefetcher(Sampler(), CPU, depth=1) as prefetch:
        item = prefetch.get(timeout=30)
    obs, next_obs = item.device["obs"], item.device["next_obs"]
    assert obs.untyped_storage().data_ptr() == next_obs.untyped_storage().data_ptr()
    assert transfer_keys(item.host, ("obs", "next_obs", "reward")) == ("window", "reward")
    assert transfer_keys({"obs": 0, "next_obs": 0}, ("obs", "next_obs")) == ("obs", "next_obs")


def test_a_returned_batch_keeps_its_values_while_later_batches_reuse_the_staging_slots():
    with DevicePrefetcher(Sampler(), CPU, depth=1) as prefetch:
        first = prefetch.get(timeout=30)
        kept = first.device["reward"].clone()
        slots_before = [dict(s.buffers) for s in prefetch._slots]
        for _ in range(5):  # two slots: each refilled twice
            prefetch.get(timeout=30)
        assert all(
            after.buffers[k] is before[k]
            for before, after in zip(slots_before, prefetch._slots, strict=True)
            for k in before
        )
    assert torch.equal(first.device["reward"], kept)


def test_the_queue_bounds_how_far_sampling_runs_ahead():
    sampler = Sampler()
    with DevicePrefetcher(sampler, CPU, depth=2):
        sampler.wait_calls(3)  # two queued and one staged, waiting for room
        time.sleep(0.3)  # room for a fourth call, if the bound did not hold
        assert sampler.calls == 3


def test_a_replay_that_is_not_ready_is_asked_again():
    sampler = Sampler(none_every=2)
    with DevicePrefetcher(sampler, CPU, depth=2, idle_s=0.001) as prefetch:
        rewards = [prefetch.get(timeout=30).device["reward"][0].item() for _ in range(3)]
    assert rewards == [0.0, 1.0, 2.0]


def test_a_sampling_error_reaches_the_consumer():
    def broken():
        raise OSError("replay gone")

    with DevicePrefetcher(broken, CPU) as prefetch:
        with pytest.raises(PrefetchError) as info:
            prefetch.get(timeout=30)
        assert isinstance(info.value.__cause__, OSError)
        with pytest.raises(PrefetchError):  # and again, not a hang
            prefetch.get(timeout=30)


def test_get_times_out_with_none_and_close_ends_a_blocked_thread():
    never = DevicePrefetcher(lambda: None, CPU, idle_s=0.001).start()
    assert never.get(timeout=0.05) is None
    never.close()
    assert not never._thread.is_alive()
    full = DevicePrefetcher(Sampler(), CPU, depth=1).start()
    full.get(timeout=30)
    full.close()
    assert not full._thread.is_alive()


def test_a_new_batch_shape_remakes_the_staging_buffers():
    sizes = itertools.chain([4, 4], itertools.repeat(6))
    with DevicePrefetcher(lambda: make_batch(0, b=next(sizes)), CPU, depth=1) as prefetch:
        shapes = [prefetch.get(timeout=30).device["action"].shape[0] for _ in range(5)]
    assert shapes == [4, 4, 6, 6, 6]


def test_depth_must_be_positive():
    with pytest.raises(ValueError, match="depth"):
        DevicePrefetcher(Sampler(), CPU, depth=0)
