"""The replay library: deduplicated, delta-compressed, rate-limited, durable pixel replay.

Both runners use it: `nasa train` holds a store in process, the replay service
serves one over Zenoh. Reading goes through a client (client.py), writing through
an adder (adder.py).
"""

from shared.replay.log import StoreFormatError
from shared.replay.rate_limiter import RateLimiterClosed, SampleToInsertRatio
from shared.replay.store import ReplayStore, open_store

__all__ = ["RateLimiterClosed", "ReplayStore", "SampleToInsertRatio", "StoreFormatError", "open_store"]
