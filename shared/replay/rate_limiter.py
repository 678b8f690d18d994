"""Samples-per-insert rate limiter with Reverb's SampleToInsertRatio semantics.

Let diff = inserts * samples_per_insert - samples. After `min_size_to_sample`
inserts, samples may proceed while diff stays >= spi * min_size - error_buffer
and inserts while diff stays <= spi * min_size + error_buffer; whichever side
runs ahead blocks. Before min_size, inserts never block and samples always do.
With G updates per env step, count one sample per update and one insert per env
step (over all writers) and set samples_per_insert = G. `extra_samples` moves the window by a
schedule's samples beyond the ratio (SAC-AE's warm-up burst, shared.schedule.limiter_extra): once
min_size is reached samples may run that many further ahead, and inserts wait for them.

Inserts check and commit in separate calls (await_insert then insert), so
concurrent writers can overshoot the bound by one call each; the error buffer
absorbs that. Samples check and count in one call (take_sample): the replay's
sampler threads never both take the last allowed sample, so a run ends with
exactly G samples per insert after the warm-up. close() wakes every waiter: a
waiter returns by raising RateLimiterClosed, so shutdown never deadlocks.
"""

from __future__ import annotations

import threading
import time


class RateLimiterClosed(RuntimeError):
    """The rate limiter was closed while (or before) waiting on it."""


class SampleToInsertRatio:
    def __init__(
        self, samples_per_insert: float, min_size_to_sample: int, error_buffer: float,
        extra_samples: int = 0,
    ) -> None:
        if samples_per_insert <= 0:
            raise ValueError(f"samples_per_insert must be > 0, got {samples_per_insert}")
        if min_size_to_sample < 1:
            raise ValueError(f"min_size_to_sample must be >= 1, got {min_size_to_sample}")
        # Both sides block at once where diff > max_diff - spi and diff < min_diff + 1: a window
        # of 2 * error_buffer must hold one insert's samples and one sample more.
        if 2 * error_buffer < samples_per_insert + 1.0:
            raise ValueError(
                f"error_buffer {error_buffer} too small: need 2 * error_buffer >= "
                f"samples_per_insert + 1 = {samples_per_insert + 1.0} or both sides can block"
            )
        self.samples_per_insert = float(samples_per_insert)
        self.min_size_to_sample = int(min_size_to_sample)
        self.error_buffer = float(error_buffer)
        # The window keeps its width, so the bound above still rules out both sides blocking.
        center = self.samples_per_insert * self.min_size_to_sample - extra_samples
        self.min_diff = center - self.error_buffer
        self.max_diff = center + self.error_buffer
        self.inserts = 0
        self.samples = 0
        self.closed = False
        self._cv = threading.Condition()

    def _diff(self) -> float:
        return self.inserts * self.samples_per_insert - self.samples

    def can_insert(self, n: int = 1) -> bool:
        if self.inserts + n <= self.min_size_to_sample:
            return True
        return self._diff() + n * self.samples_per_insert <= self.max_diff

    def can_sample(self, n: int = 1) -> bool:
        if self.inserts < self.min_size_to_sample:
            return False
        return self._diff() - n >= self.min_diff

    def _await(self, ok, timeout: float | None, then=None) -> bool:  # noqa: ANN001
        """Wait until ok(); then run `then` (if given) under the same lock and return True."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cv:
            while True:
                if self.closed:
                    raise RateLimiterClosed("rate limiter closed")
                if ok():
                    if then is not None:
                        then()
                    return True
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._cv.wait(remaining)

    def await_insert(self, timeout: float | None = None, n: int = 1) -> bool:
        """Block until n inserts are allowed; False on timeout, RateLimiterClosed if closed."""
        return self._await(lambda: self.can_insert(n), timeout)

    def take_sample(self, n: int = 1, timeout: float | None = None) -> bool:
        """Block until n samples are allowed and count them, atomically; False on timeout,
        RateLimiterClosed if closed."""

        def count() -> None:
            self.samples += n
            self._cv.notify_all()

        return self._await(lambda: self.can_sample(n), timeout, count)

    def insert(self, n: int = 1) -> None:
        with self._cv:
            self.inserts += n
            self._cv.notify_all()

    def restore(self, inserts: int, samples: int) -> None:
        """Set the counts a restarted process had reached (e.g. from its store); wakes waiters."""
        if inserts < 0 or samples < 0:
            raise ValueError(f"counts must be >= 0, got inserts={inserts}, samples={samples}")
        with self._cv:
            self.inserts, self.samples = int(inserts), int(samples)
            self._cv.notify_all()

    def lower_samples(self, samples: int) -> None:
        """Count `samples` samples if that is fewer than counted (a restarted learner lost the
        updates of the samples it drew after its checkpoint); wakes waiters."""
        with self._cv:
            self.samples = max(0, min(self.samples, int(samples)))
            self._cv.notify_all()

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()

    def stats(self) -> dict:
        with self._cv:
            return {
                "inserts": self.inserts,
                "samples": self.samples,
                "diff": self._diff(),
                "min_diff": self.min_diff,
                "max_diff": self.max_diff,
                "closed": self.closed,
            }
