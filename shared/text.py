"""Text made fit for a bounded place: a log line, an error message, a wire field."""

from __future__ import annotations


def clip(text: str, limit: int) -> str:
    """`text` whole if it has at most `limit` characters, else its start ending in "..." (`limit`
    characters in all), so a reader sees that something was cut."""
    return text if len(text) <= limit else text[:limit - 3] + "..."
