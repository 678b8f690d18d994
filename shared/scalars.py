"""TensorBoard event files of a run, the same tags for both runners (`tensorboard --logdir <data>`).

`nasa train` writes <out>/tensorboard/train, the learner
<data>/tensorboard/learner (and the evaluator its autoencoder images in
<data>/tensorboard/evaluator), through torch's SummaryWriter: the tensorboard
package's own format. Every point's step is the env step. Tags:

- `eval/return_mean`, `eval/return_std`: each evaluation.
- `train/episode_return`, `train/episode_length`, `train/steps_per_s` and
  `train/<metric>` for each loss and intrinsic mean of a train.csv row.
- (learner only) the fleet's figures of /status, every few seconds:
  `rates/env_steps_per_s`, `rates/updates_per_s`, `ratio/updates_per_env_step`,
  `ratio/target`, `policy_lag/mean`, `policy_lag/max`, `intrinsic/novelty_mean`,
  `intrinsic/surprise_mean`, `replay/size`, `replay/bytes`,
  `invalid_messages/learner`, `invalid_messages/replay`, `updates`.
- `autoencoder/view`: the autoencoder's view image of an evaluation.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

TENSORBOARD_DIR = "tensorboard"
ROW_SKIP = {"step", "episode", "return", "length", "updates", "wall_s", "steps_per_s"}
RETRY_S = 60.0
"""After a write the disk refused, points are dropped this long before a new event file is tried."""
EVENT_FILES = "events.out.tfevents.*"


def _number(v: object) -> float | None:
    if isinstance(v, bool):
        return float(v)
    if isinstance(v, int | float) and math.isfinite(float(v)):
        return float(v)
    return None


def status_scalars(s: dict) -> dict[str, float | None]:
    """The fleet figures of one /status, by tag."""
    lag, intrinsic, replay = s["policy_lag"], s["intrinsic"], s["replay"]
    return {
        "rates/env_steps_per_s": s["env_steps_per_s"], "rates/updates_per_s": s["updates_per_s"],
        "ratio/updates_per_env_step": s["updates_per_env_step"],
        "ratio/target": s["updates_target_per_env_step"],
        "policy_lag/mean": lag["mean"], "policy_lag/max": lag["max"],
        "intrinsic/novelty_mean": intrinsic["novelty_mean"],
        "intrinsic/surprise_mean": intrinsic["surprise_mean"],
        "replay/size": replay["size"], "replay/bytes": replay["bytes"],
        "invalid_messages/learner": s["invalid_messages"],
        "invalid_messages/replay": replay["invalid_messages"],
        "updates": s["updates"],
        **{f"loss/{k}": v for k, v in s["losses"].items()},
    }


def _holds_points(path: Path) -> bool:
    """Whether an event file holds a point (a scalar or an image), not only the header every new
    file starts with; a record cut short ends the reading."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    try:
        return any(event.HasField("summary") for event in EventFileLoader(str(path)).Load())
    except Exception:  # noqa: BLE001 -- a file it cannot read is kept, not judged empty
        return True


def _quiet_writer_threads() -> None:
    """Keep an OSError in tensorboard's writing thread (a full disk) from printing a traceback:
    the writer raises it again at the next add, flush or close, where the runner reports it."""
    if getattr(threading.excepthook, "quiet_writer_threads", False):
        return
    previous = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        if isinstance(args.exc_value, OSError) and type(args.thread).__name__ == "_AsyncWriterThread":
            return
        previous(args)

    hook.quiet_writer_threads = True
    threading.excepthook = hook


class Scalars:
    """A SummaryWriter opened on first use (importing tensorboard costs a second or two)."""

    def __init__(self, logdir: Path, flush_secs: int = 10) -> None:
        self.logdir, self.flush_secs = Path(logdir), flush_secs
        # A resumed run: events from this step on are dropped; written by the first writer whose
        # file keeps a point, not again.
        self.purge_step: int | None = None
        self._writer = None
        self._file: Path | None = None  # the event file the writer made
        self._refused_at: float | None = None  # when the disk last refused a write
        self.refused = 0  # writes the disk refused, each raised once

    @property
    def refusing(self) -> bool:
        """Whether the last write was refused (points are dropped until a new file takes them)."""
        return self._refused_at is not None

    @property
    def writer(self):  # noqa: ANN201 (torch.utils.tensorboard.SummaryWriter, imported lazily)
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            _quiet_writer_threads()
            before = self._event_files()
            try:
                self._writer = SummaryWriter(str(self.logdir), flush_secs=self.flush_secs,
                                             purge_step=self.purge_step)
            finally:  # made even where the disk refused its first record
                self._file = next(iter(self._event_files() - before), None)
        return self._writer

    def _event_files(self) -> set[Path]:
        try:
            return set(self.logdir.glob(EVENT_FILES))
        except OSError:
            return set()

    def _drop_file_without_points(self) -> None:
        """Remove the event file of a writer given up on if it holds no point: each retry on a disk
        still refusing makes a file, and a long spell of them would leave a file a minute."""
        path, self._file = self._file, None
        if path is None:
            return
        if _holds_points(path):
            # It holds the resumed run's purge marker, written ahead of its points: a later writer's
            # marker would hide the points written since. A file dropped takes its marker with it.
            self.purge_step = None
        else:
            with contextlib.suppress(OSError):
                path.unlink()

    def _write(self, write: Callable[[object], None]) -> None:
        """`write(writer)`. The OSError of a refused write (a full disk) is raised once, for the
        runner to stop or go on: the writer's thread ended with it and would raise it at every later
        call, so the writer is dropped (and its file, if it took no point), points are dropped for
        RETRY_S, and then a new file is tried."""
        if self._refused_at is not None and time.monotonic() - self._refused_at < RETRY_S:
            return
        self._refused_at = None
        try:
            write(self.writer)
        except OSError:
            self._writer, self._refused_at = None, time.monotonic()
            self.refused += 1
            self._drop_file_without_points()
            raise

    def add(self, values: dict[str, object], step: int) -> None:
        points = [(tag, v) for tag, value in values.items() if (v := _number(value)) is not None]

        def add_all(writer) -> None:  # noqa: ANN001
            for tag, v in points:
                writer.add_scalar(tag, v, int(step))

        self._write(add_all)

    def eval(self, step: int, mean: float, std: float) -> None:
        self.add({"eval/return_mean": mean, "eval/return_std": std}, step)

    def episode(self, row: dict) -> None:
        """A train.csv row: its episode's return and length, and each metric mean it carries."""
        values = {"train/episode_return": row["return"], "train/episode_length": row["length"],
                  "train/steps_per_s": row.get("steps_per_s")}
        values |= {f"train/{k}": v for k, v in row.items() if k not in ROW_SKIP}
        self.add(values, row["step"])

    def status(self, s: dict) -> None:
        self.add(status_scalars(s), s["env_steps"])

    def image(self, tag: str, image: np.ndarray, step: int) -> None:
        """An (H, W, 3) uint8 image."""
        self._write(lambda writer: writer.add_image(tag, image, int(step), dataformats="HWC"))

    def flush(self) -> None:
        if self._writer is not None:
            self._write(lambda writer: writer.flush())

    def close(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()  # may raise the error its writing thread met (a full disk), once
