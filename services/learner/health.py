"""The learner's flags and the reasons its /healthz gives (empty: healthy)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from shared.zenoh_session import ServiceArgs, env_int

if TYPE_CHECKING:
    from services.learner.core import LearnerCore
    from shared.service import StopFlag


@dataclass
class LearnerArgs(ServiceArgs):
    """The learner: updates the agent from replay batches, publishes weights, serves /status."""

    data: Path = field(default_factory=lambda: Path(os.environ.get("NASA_DATA", "runs/default")))
    """Run folder: eval.csv, train.csv, learner/checkpoint.pt, learner/status.json (env NASA_DATA)."""
    host: str = field(default_factory=lambda: os.environ.get("NASA_STATUS_HOST", "127.0.0.1"))
    """Address of the status API (env NASA_STATUS_HOST; 0.0.0.0 in a container)."""
    port: int = field(default_factory=lambda: env_int("NASA_STATUS_PORT", 8000))
    """Port of the status API (env NASA_STATUS_PORT)."""
    api_token_file: Path | None = None
    """File whose first line is the bearer token of POST /control/* (env NASA_API_TOKEN wins).
    Neither: the controls are open to whoever reaches the port. A file that cannot be read or whose
    first line is empty is refused at start."""
    publish_every: int = 20
    """K: publish weights every K updates."""
    prefetch: int = 2
    """Sample requests kept in flight."""
    device_prefetch: str = "auto"
    """Stage batches on the learner's device ahead of the update (pinned buffers, copies on a side
    stream: shared/prefetch.py): `on`, `off`, or `auto` (on with CUDA, where the copy can overlap
    the update; off on the CPU, where it would only add a copy)."""
    score_ahead: bool = True
    """Collect timing: a thread asks the replay for the rows owed a score while the update runs, so
    the update does not wait on that round trip (the rows are scored an update or two later than
    they would be with `--no-score-ahead`, which asks before each update)."""
    final_eval_wait_s: float = 300.0
    """At the end, how long to wait for the evaluation of the last eval step (while no evaluator is
    alive, only a short grace for one to come back)."""
    eval_between_updates: bool = False
    """Evaluate in this process between updates, as `nasa train` does, for a run without an
    evaluator service (services/learner/evaluation.py)."""
    threads: int = 0
    """torch threads (0: torch's default)."""
    stall_s: float = 120.0
    """/healthz: unhealthy when no update came for this long while the replay holds learning steps."""
    max_skipped_updates: int = 100
    """/healthz: unhealthy beyond this many updates skipped for non-finite losses or gradients."""
    actor_restarts: int = 3
    """/healthz: unhealthy when an actor restarted more than this often within crash_window_s."""
    crash_window_s: float = 300.0


def health_reasons(core: LearnerCore, a: LearnerArgs, stop: StopFlag) -> list[str]:
    """Stopping, stalled training, too many skipped updates, a replay that cannot write, a failed
    checkpoint, an actor that crash-loops: each a reason /healthz answers 503 with."""
    board = core.board
    reasons = [f"stopping ({stop.reason})"] if stop else []
    idle = time.monotonic() - board.last_update
    if board.env_steps > core.config.warmup_steps and not core.done() and idle > a.stall_s \
            and not board.evaluating:
        reasons.append(f"training stalled: no update for {idle:.0f} s with {board.env_steps} env steps "
                       f"stored")
    if board.skipped_updates > a.max_skipped_updates:
        reasons.append(f"{board.skipped_updates} updates skipped for non-finite losses or gradients")
    if board.replay["write_error"]:
        reasons.append(f"the replay cannot write: {board.replay['write_error']}")
    # A checkpoint the disk refused is degraded (degraded_reasons): a restart, which a liveness probe
    # makes of a 503, would lose the updates since the last one and meet the same disk.
    if core.checkpoint_error and "checkpoint" not in board.writes.failing():
        reasons.append(f"checkpoint not written: {core.checkpoint_error}")
    if looping := board.crash_looping(a.actor_restarts, a.crash_window_s):
        reasons.append(f"actor(s) {looping} restarted more than {a.actor_restarts} times in "
                       f"{a.crash_window_s:.0f} s")
    return reasons


def degraded_reasons(core: LearnerCore) -> list[str]:
    """The run folder's writes the disk refuses still (CSV rows, TensorBoard points, checkpoints):
    the learner trains on, dropping them, so /healthz answers degraded, not unhealthy."""
    writes = core.board.writes
    if not (failing := writes.failing()):
        return []
    return [f"writes failing: {', '.join(failing)} (last: {writes.last_error})"]
