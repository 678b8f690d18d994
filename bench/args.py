"""Command-line types the benchmarks share: a bad task or algorithm is refused as argparse refuses
a bad flag (one line, exit 2), before any process starts, not by a service that exits while the
benchmark waits for it."""

from __future__ import annotations

import argparse

from shared.config import ALGOS

__all__ = ["ALGOS", "task_name", "task_names"]


def task_name(text: str) -> str:
    """An argparse type: a task some environment source owns."""
    from shared.envs import UnknownTaskError, check_task

    try:
        check_task(text)
    except UnknownTaskError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def task_names(text: str) -> list[str]:
    """An argparse type: comma-separated tasks, each one some environment source owns."""
    return [task_name(name) for name in text.split(",")]
