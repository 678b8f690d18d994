"""Replay store: deduplicated, delta-compressed, rate-limited, durable pixel replay."""

from services.replay.log import StoreFormatError
from services.replay.rate_limiter import RateLimiterClosed, SampleToInsertRatio
from services.replay.store import ReplayStore

__all__ = ["RateLimiterClosed", "ReplayStore", "SampleToInsertRatio", "StoreFormatError"]
