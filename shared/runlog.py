"""The run folder's CSV files: eval.csv and train.csv.

Both runners (the single-process trainer and the learner service) write them
through this module, so a plot never cares which runner made a run.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

from shared.config import ConfigError

TRAIN_FIELDS = (
    "step", "episode", "return", "length", "novelty_mean", "surprise_mean",
    "critic_loss", "actor_loss", "ae_loss", "ensemble_loss", "updates", "steps_per_s", "wall_s",
)


def eval_fields(episodes: int) -> list[str]:
    """eval.csv's columns: the env step evaluated, the update count of the weights that played it,
    the mean, population std, min and max of the episodes' extrinsic returns, and each return."""
    return ["step", "updates", "mean", "std", "min", "max", *(f"return_{i}" for i in range(episodes))]


def older_eval_fields(episodes: int) -> list[list[str]]:
    """eval.csv headers of earlier versions, which a resumed run continues under (CsvLog `older`)."""
    return [["step", "mean", "std", *(f"return_{i}" for i in range(episodes))]]


class RunLogError(ConfigError):
    """A run's CSV file that cannot be continued: damaged, or not the one these settings write."""


class CsvLog:
    """An append-only CSV with a fixed header; rows are flushed at once.

    An existing file is continued only if it starts with this header, or with one of `older` (the
    header an earlier version wrote: its rows go on under it, without the columns it lacks, as
    rewriting the file on a full disk could lose it): a damaged or foreign file is refused, named,
    and left as it is, so resuming never writes rows under another header.
    """

    def __init__(self, path: str | Path, fields: list[str] | tuple[str, ...],
                 older: list[list[str]] | None = None) -> None:
        self.path = Path(path)
        self.fields = list(fields)
        self.known = set(self.fields)  # what a row may hold, whatever header the file has
        if not self.path.exists() or self.path.stat().st_size == 0:  # empty: nothing to lose
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self.fields)
            return
        with open(self.path, "rb") as f:
            first = f.readline()
        try:
            header = next(csv.reader([first.decode("utf-8")]), [])
        except UnicodeDecodeError:
            header = None
        if header in (older or []):
            self.fields = list(header)
        elif header != self.fields:
            raise RunLogError(
                f"{self.path} does not start with the header this run writes "
                f"({','.join(self.fields)}): it is damaged or from other settings; "
                "move it aside to continue the run without it"
            )
        self._cut_torn_row()

    def _cut_torn_row(self) -> None:
        """Drop a last row its writer did not finish (it died mid-write): the next row would
        otherwise be appended onto it, and both be lost."""
        data = self.path.read_bytes()
        if data.endswith(b"\n"):
            return
        end = data.rfind(b"\n") + 1
        with open(self.path, "r+b") as f:
            if end == 0:  # the header alone, unterminated
                f.seek(len(data))
                f.write(b"\r\n")
            else:
                f.truncate(end)

    def append(self, row: dict) -> None:
        unknown = set(row) - self.known
        if unknown:
            raise ValueError(f"{self.path.name}: unknown fields {sorted(unknown)}")
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerow([_format(row.get(k)) for k in self.fields])

    def sync(self) -> None:
        """fsync the file: a checkpoint that counts its rows must not outlive them on a power loss."""
        with open(self.path, "rb") as f:
            os.fsync(f.fileno())

    # Lines are counted and cut as bytes: a damaged byte in a row must not stop a resume that
    # drops that row anyway.
    def rows(self) -> int:
        with open(self.path, "rb") as f:
            return sum(1 for _ in f) - 1

    def truncate(self, rows: int) -> None:
        """Keep the header and the first `rows` rows (a resumed run drops what came after its checkpoint)."""
        # Cut in place, never rewritten: a rewrite on a full disk would lose the rows it keeps.
        with open(self.path, "r+b") as f:
            end = 0
            for _ in range(rows + 1):
                if not (line := f.readline()):
                    return
                end += len(line)
            f.truncate(end)


def eval_walls(run: str | Path, steps: list[int]) -> dict[int, float]:
    """Wall-clock seconds of the run at which each of its evaluated `steps` was reached: the end of
    the first training episode at or after it (train.csv's wall_s); step 0 at 0. A step no episode
    reached yet has none."""
    train = Path(run) / "train.csv"
    episodes = read_rows(train, whole=True) if train.exists() else []
    ends = [(int(e["step"]), float(e["wall_s"])) for e in episodes if e.get("wall_s")]
    out: dict[int, float] = {}
    for step in steps:
        wall = 0.0 if step == 0 else next((w for s, w in ends if s >= step), None)
        if wall is not None:
            out[step] = wall
    return out


def read_rows(path: str | Path, whole: bool = False) -> list[dict[str, str]]:
    """The rows of a CSV file. `whole`: without a last row that has no line end, one its writer did
    not finish (it died mid-write, or the file was cut short): its values may be cut too, and a
    resume drops it (CsvLog). A file the csv module cannot parse (a field past its length limit: a
    binary blob, an unclosed quote) is a ValueError naming it, like any other damaged value."""
    with open(path, newline="") as f:
        text = f.read()
    if whole and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    try:
        return list(csv.DictReader(io.StringIO(text, newline="")))
    except csv.Error as err:
        raise ValueError(f"{path}: not a CSV file this version can read ({err})") from None


def checkpointed_step(run: str | Path, checkpoint_every: int) -> int | None:
    """The step of the first checkpoint the run folder's train.csv shows was written, or None (no
    row past it, or a file that cannot be read). A runner checkpoints at the end of its first episode
    at or past checkpoint_every steps, so a row after that episode's means the checkpoint was
    written: if checkpoint.pt is gone, a resume would start the run over and clear its rows."""
    try:
        steps = [int(float(row["step"])) for row in read_rows(Path(run) / "train.csv", whole=True)]
    except (OSError, ValueError, KeyError, TypeError, OverflowError):
        return None
    return next((step for step in steps[:-1] if step >= checkpoint_every), None)


def _format(value: object) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
