"""`nasa plot`: learning curves and a results table from a folder of runs.

Finds every eval.csv under a results folder, names each run by its config.json
("algo", "seed", "env"["task"]) or else by the layout `nasa reproduce` writes
(<task>/<algo>/seed<S>), and writes:

- curves.png, curves.svg: one panel per task, one line per algorithm and
  runner (a run of the distributed system, `nasa up`, is told by the learner/
  folder it leaves, and drawn as "<algo>, nasa up"): the mean
  over seeds of the evaluation return, with a band of +-1 standard deviation
  over seeds (population std). Where every seed was evaluated at the same
  steps the curve is drawn at those; where their steps differ (an evaluator
  that skipped a step, another eval_every), each seed is interpolated
  linearly onto every step any of them was evaluated at, and the caption says
  so. A curve stops where its shortest seed stops. Runs of one task with
  different action repeats are separate series. A dotted line marks the
  untrained policy's return (the evaluation at step 0, mean over the task's
  runs). The x axis: env steps (`--x steps`: one step is one action, held for
  `action_repeat` simulator frames; the label gives the action repeat),
  frames (`--x frames`: steps x action repeat, the axis of SAC-AE's and DrQ's
  published figures, and of the paper's, which has no action repeat), or the
  run's wall-clock time at which each evaluated step was reached (`--x
  minutes`, train.csv), to compare runners.
- results.md: per task and algorithm, the final return (mean +- std over seeds
  of each seed's last evaluation), the best return (mean over seeds of each
  seed's best evaluation), the number of seeds, the action repeat, the last
  step and frame, and the paper's approximate figure at 1M steps without
  action repeat (1M frames) where the paper gives one (docs/reference.md).
"""

from __future__ import annotations

import math
import os
import re
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NoReturn

import numpy as np
import tyro

from shared.config import ALGOS, ConfigError
from shared.envs import PAPER_TASKS
from shared.run_config import read_json_object
from shared.runlog import eval_walls, read_rows
from shared.service import read_flags

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Approximate final returns at 1M steps read off the paper's figure (docs/reference.md).
# The paper gives no Pixel-TD3 figure.
PAPER_FINAL: dict[str, dict[str, float]] = {
    "ball_in_cup-catch": {"nasa_td3": 950, "sac_ae": 950, "td3_ae": 950},
    "cartpole-balance": {"nasa_td3": 950, "sac_ae": 970, "td3_ae": 950},
    "reacher-hard": {"nasa_td3": 600, "sac_ae": 80, "td3_ae": 80},
    "finger-spin": {"nasa_td3": 970, "sac_ae": 980, "td3_ae": 910},
    "walker-walk": {"nasa_td3": 950, "sac_ae": 950, "td3_ae": 450},
    "cheetah-run": {"nasa_td3": 570, "sac_ae": 280, "td3_ae": 360},
}
BAND = "band: +-1 std over seeds"
X_LABELS = {"frames": "frames (env steps x action repeat)", "minutes": "wall-clock minutes"}


@dataclass
class SeedCurve:
    """One run's evaluation curve."""

    task: str
    algo: str
    seed: int
    steps: np.ndarray
    means: np.ndarray
    path: Path
    runner: str = "train"
    """`train` (nasa train, nasa reproduce) or `up` (the distributed system)."""
    walls: np.ndarray | None = None
    """Wall-clock seconds at which each step was reached (NaN: not known)."""
    action_repeat: int | None = None
    """Simulator frames per env step (config.json's env.action_repeat; None: not known)."""

    @property
    def series(self) -> str:
        """The curve's name in a panel: the algorithm, and the runner when it is the distributed one."""
        return self.algo if self.runner == "train" else f"{self.algo}, nasa up"


@dataclass
class Summary:
    """One task/algorithm row of the results table."""

    task: str
    algo: str
    seeds: int
    last_steps: tuple[int, int]
    """(min, max) over seeds of each seed's last evaluated step."""
    final_mean: float
    final_std: float
    best_mean: float
    paper: float | None
    action_repeat: int | None = None
    """The series' action repeat (None: not known)."""

    @property
    def last_frames(self) -> tuple[int, int] | None:
        """(min, max) over seeds of each seed's last evaluated frame (None: action repeat unknown)."""
        if self.action_repeat is None:
            return None
        return self.last_steps[0] * self.action_repeat, self.last_steps[1] * self.action_repeat


def run_identity(folder: Path) -> tuple[str, str, int] | None:
    """(task, algo, seed) of a run folder: from config.json, else from <task>/<algo>/seed<S>."""
    config_path = folder / "config.json"
    if config_path.exists():
        config = read_json_object(config_path, what="a run's config")
        env = config.get("env")
        task = env.get("task") if isinstance(env, dict) else None
        if task is not None and "algo" in config and "seed" in config:
            algo = config["algo"]
            if not isinstance(task, str) or not isinstance(algo, str):
                raise ConfigError(
                    f"{config_path}: env.task and algo must be names, got {task!r} and {algo!r}")
            return task, algo, int(config["seed"])
    if folder.name.startswith("seed") and folder.name[4:].isdigit():
        return folder.parent.parent.name, folder.parent.name, int(folder.name[4:])
    return None


def action_repeat_of(folder: Path) -> int | None:
    """The run's env.action_repeat from its config.json, or None where it has none."""
    config_path = folder / "config.json"
    if not config_path.exists():
        return None
    env = read_json_object(config_path, what="a run's config").get("env")
    repeat = env.get("action_repeat") if isinstance(env, dict) else None
    if repeat is None:
        return None
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise ConfigError(f"{config_path}: env.action_repeat must be a whole number from 1, got {repeat!r}")
    return repeat


def find_runs(results_dir: Path, walls: bool = False) -> list[SeedCurve]:
    """Every eval.csv under `results_dir` with at least one row and a known task/algo/seed, with
    the wall-clock time of each step (train.csv) when `walls`. A run whose files cannot be read (a
    damaged file, a row cut short, a step or return that is inf or nan, steps out of order) is named
    and skipped, so one bad folder does not hide the others' curves; train.csv is read only for
    `walls`, so its damage hides no step curve."""
    runs: list[SeedCurve] = []
    seen: dict[tuple[str, str, int, str], Path] = {}
    for path in sorted(Path(results_dir).rglob("eval.csv")):
        try:
            identity = run_identity(path.parent)
            if identity is None:
                print(f"nasa plot: skipping {path}: no config.json and not under <task>/<algo>/seed<S>",
                      file=sys.stderr)
                continue
            rows = read_rows(path, whole=True)  # a row cut short may hold a cut-short return
            if not rows:
                continue  # a run that has not evaluated yet
            steps = np.array([float(r["step"]) for r in rows])
            means = np.array([float(r["mean"]) for r in rows])
            if not (np.isfinite(steps).all() and np.isfinite(means).all()):
                # One seed's inf or nan would make its task's whole row and curve inf or nan.
                raise ValueError("a step or mean that is not a finite number")
            if (np.abs(steps) >= 2**62).any():  # beyond any run, and near int64's end
                raise ValueError("a step out of range")
            if (np.diff(steps) <= 0).any():  # align interpolates along the file's order
                raise ValueError("steps not in increasing order (eval.csv is written in step order)")
            steps = steps.astype(np.int64)
            repeat = action_repeat_of(path.parent)
            at = eval_walls(path.parent, steps.tolist()) if walls else {}
        except ConfigError as err:
            print(f"nasa plot: skipping {path}: {err}", file=sys.stderr)
            continue
        except (OSError, UnicodeDecodeError, ValueError, TypeError, KeyError, OverflowError) as err:
            print(f"nasa plot: skipping {path}: unreadable ({type(err).__name__}: {err})", file=sys.stderr)
            continue
        runner = "up" if (path.parent / "learner").is_dir() else "train"
        if (*identity, runner) in seen:
            print(f"nasa plot: skipping {path}: same task/algo/seed/runner as {seen[(*identity, runner)]}",
                  file=sys.stderr)
            continue
        seen[(*identity, runner)] = path
        runs.append(SeedCurve(*identity, steps=steps, means=means, path=path, runner=runner,
                              walls=np.array([at.get(int(s), np.nan) for s in steps]),
                              action_repeat=repeat))
    return runs


def with_frames(runs: list[SeedCurve]) -> list[SeedCurve]:
    """The runs whose action repeat is known (a frame axis needs it); the others are named."""
    known = [r for r in runs if r.action_repeat is not None]
    for r in runs:
        if r.action_repeat is None:
            print(f"nasa plot: skipping {r.path} on the frames axis: no env.action_repeat in a config.json",
                  file=sys.stderr)
    return known


def _order(names: set[str], preferred: tuple[str, ...]) -> list[str]:
    """The paper's order first, then anything else alphabetically."""
    return [n for n in preferred if n in names] + sorted(names - set(preferred))


def _series_order(names: set[str]) -> list[str]:
    """Series by algorithm in the paper's order, then by what follows it ("nasa up", the action
    repeat) with numbers in numeric order (action repeat 5 before 25)."""
    def key(name: str) -> tuple:
        algo, _, rest = name.partition(", ")
        rank = ALGOS.index(algo) if algo in ALGOS else len(ALGOS)
        return rank, algo, [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", rest)]
    return sorted(names, key=key)


def series_name(run: SeedCurve, split_repeat: bool) -> str:
    """The run's series; with `split_repeat` (its task has runs of several action repeats, whose
    steps are not the same amount of experience) the action repeat too."""
    if not split_repeat:
        return run.series
    return f"{run.series}, action repeat {'?' if run.action_repeat is None else run.action_repeat}"


def group(runs: list[SeedCurve]) -> dict[str, dict[str, list[SeedCurve]]]:
    """task -> series (algorithm, runner, and action repeat where the task's runs differ in it) ->
    seed curves, tasks and algorithms in the paper's order."""
    out: dict[str, dict[str, list[SeedCurve]]] = {}
    for task in _order({r.task for r in runs}, PAPER_TASKS):
        of_task = [r for r in runs if r.task == task]
        split = len({r.action_repeat for r in of_task}) > 1
        names = {series_name(r, split) for r in of_task}
        out[task] = {
            name: sorted((r for r in of_task if series_name(r, split) == name), key=lambda r: r.seed)
            for name in _series_order(names)
        }
    return out


def same_steps(curves: list[SeedCurve]) -> bool:
    """Whether every seed was evaluated at the same steps over the span `align` draws (from the
    latest first step to the shortest seed's last)."""
    start = max(int(c.steps[0]) for c in curves)
    end = min(int(c.steps[-1]) for c in curves)
    first = curves[0].steps[(curves[0].steps >= start) & (curves[0].steps <= end)].tolist()
    return all(c.steps[(c.steps >= start) & (c.steps <= end)].tolist() == first for c in curves)


def align(curves: list[SeedCurve]) -> tuple[np.ndarray, np.ndarray]:
    """(steps, values[seed, step]) on a grid common to the seeds, up to the shortest seed's last
    step: the steps they were evaluated at where these are the same; else every step any of them
    was evaluated at from the latest first step, each seed interpolated linearly between its own
    evaluations (its steps are ascending: eval.csv is written in step order)."""
    start = max(int(c.steps[0]) for c in curves)
    end = min(int(c.steps[-1]) for c in curves)
    grid = np.unique(np.concatenate([c.steps[(c.steps >= start) & (c.steps <= end)] for c in curves]))
    return grid.astype(int), np.array([np.interp(grid, c.steps, c.means) for c in curves])


def untrained(curves: list[SeedCurve]) -> float | None:
    """Mean return of the evaluations at step 0 (the untrained policy), or None if none has one."""
    first = [float(c.means[0]) for c in curves if len(c.steps) and c.steps[0] == 0]
    return float(np.mean(first)) if first else None


def summarize(runs: list[SeedCurve]) -> list[Summary]:
    rows = []
    for task, by_algo in group(runs).items():
        for algo, curves in by_algo.items():
            final = np.array([c.means[-1] for c in curves])
            best = np.array([c.means.max() for c in curves])
            last = [int(c.steps[-1]) for c in curves]
            repeats = {c.action_repeat for c in curves}  # one: a series holds one action repeat
            rows.append(Summary(
                task, algo, len(curves), (min(last), max(last)),
                float(final.mean()), float(final.std()), float(best.mean()),
                PAPER_FINAL.get(task, {}).get(curves[0].algo),
                repeats.pop() if len(repeats) == 1 else None,
            ))
    return rows


def results_table(summaries: list[Summary]) -> str:
    """The results as a markdown table."""
    lines = [
        "| task | algo | seeds | action repeat | last step | last frame | final return | best return "
        "| paper @1M frames |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summaries:
        repeat = "?" if s.action_repeat is None else str(s.action_repeat)
        frames = "?" if s.last_frames is None else _span(s.last_frames)
        paper = "n/a" if s.paper is None else f"~{s.paper:.0f}"
        # One seed has no spread over seeds: a "± 0.0" would read as a measured one.
        final = f"{s.final_mean:.1f}" if s.seeds == 1 else f"{s.final_mean:.1f} ± {s.final_std:.1f}"
        lines.append(
            f"| {s.task} | {s.algo} | {s.seeds} | {repeat} | {_span(s.last_steps)} | {frames} | {final} "
            f"| {s.best_mean:.1f} | {paper} |"
        )
    return "\n".join(lines) + "\n"


def _span(bounds: tuple[int, int]) -> str:
    lo, hi = bounds
    return f"{lo}" if lo == hi else f"{lo}-{hi}"


def x_values(curves: list[SeedCurve], steps: np.ndarray, x: str) -> np.ndarray:
    """The x of each aligned step: the step, its frame (step x the series' action repeat), or the
    mean over seeds of the minutes it was reached at."""
    if x == "steps":
        return steps
    if x == "frames":
        (repeat,) = {c.action_repeat for c in curves}  # a series holds one action repeat (group)
        if repeat is None:
            raise ValueError("a frames axis needs each run's action repeat (with_frames)")
        return steps * repeat
    # Each seed's clock at the grid's steps, interpolated as its returns are (align); NaN: not known.
    walls = np.array([np.interp(steps, c.steps, c.walls if c.walls is not None else c.steps * np.nan)
                      for c in curves])
    with warnings.catch_warnings():  # a step no seed's clock reached: NaN, drawn as a gap
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(walls, axis=0) / 60.0


def x_label(curves: list[SeedCurve], x: str) -> str:
    """The x axis' name; on env steps, with the panel's action repeat, which says what a step is."""
    if x != "steps":
        return X_LABELS[x]
    repeats = {c.action_repeat for c in curves}
    if len(repeats) > 1:
        return "env steps (action repeat differs between series: --x frames compares them)"
    (repeat,) = repeats
    if repeat is None:
        return "env steps (action repeat not known)"
    return f"env steps (action repeat {repeat}: {repeat} frame{'s' if repeat > 1 else ''} each)"


def plot_curves(runs: list[SeedCurve], x: str = "steps") -> Figure:
    """One panel per task, one line per algorithm and runner (mean over seeds, +-1 std band), and the
    untrained policy's return as a dotted line."""
    # Imported here: `nasa` loads this module for every subcommand, matplotlib only plots.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    grouped = group(runs)
    ncols = min(3, len(grouped))
    nrows = math.ceil(len(grouped) / ncols)
    fig = Figure(figsize=(4.5 * ncols, 3.4 * nrows + 0.8), layout="constrained")
    FigureCanvasAgg(fig)  # draw with Agg: no display, no pyplot state
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[len(grouped):]:
        fig.delaxes(ax)  # so the figure holds exactly one axes per task
    all_series = _series_order({name for by_series in grouped.values() for name in by_series})
    colors = {name: f"C{i}" for i, name in enumerate(all_series)}  # same color in every panel
    interpolated = False
    for ax, (task, by_series) in zip(axes, grouped.items(), strict=False):
        for name, curves in by_series.items():
            interpolated |= not same_steps(curves)
            steps, values = align(curves)
            mean, std = values.mean(axis=0), values.std(axis=0)
            xs = x_values(curves, steps, x)
            label = f"{name} (n={len(curves)})"
            if len(steps) and steps[-1] < max(int(c.steps[-1]) for c in curves):
                label = f"{name} (n={len(curves)}, to step {steps[-1]}: all seeds' last)"
            # One common step (a seed just started) is a point: a line of one point draws nothing.
            ax.plot(xs, mean, color=colors[name], label=label, marker="o" if len(xs) < 2 else None)
            ax.fill_between(xs, mean - std, mean + std, color=colors[name], alpha=0.2, linewidth=0)
        base = untrained([c for curves in by_series.values() for c in curves])
        if base is not None:
            ax.axhline(base, color="0.4", linestyle=":", label=f"untrained ({base:.0f})")
        ax.set_title(task)
        ax.set_xlabel(x_label([c for curves in by_series.values() for c in curves], x))
        ax.set_ylabel("evaluation return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    # Two short lines: one panel is narrow, and the caption must stay readable there.
    how = ("seeds' evaluations at different steps: each interpolated linearly onto all their steps"
           if interpolated else "seeds aligned on the steps all evaluated at")
    fig.suptitle(f"line: mean over seeds; {BAND}\n{how}", fontsize="medium")
    return fig


@dataclass
class PlotCommand:
    """Learning curves (curves.png, curves.svg) and a results table (results.md) from a results folder."""

    results: tyro.conf.Positional[Path]
    """Folder holding run folders (as `nasa reproduce` writes them, or any with a config.json)."""
    out: Path | None = None
    """Where to write the figures and table (default: the results folder)."""
    x: Literal["steps", "frames", "minutes"] = "steps"
    """The x axis: env steps (one action each), frames (env steps x action repeat: the axis of the
    paper, which has no action repeat, and of SAC-AE's and DrQ's figures), or the wall-clock minutes
    at which each step was reached."""


def plot(argv: list[str]) -> None:
    cmd = read_flags(PlotCommand, argv, "nasa plot")
    if not cmd.results.is_dir():
        _fail(f"{cmd.results} is not a folder")
    runs = find_runs(cmd.results, walls=cmd.x == "minutes")
    if cmd.x == "frames":
        runs = with_frames(runs)
    if not runs:
        _fail(f"no run with an evaluation under {cmd.results}")
    out = cmd.out or cmd.results
    fig = plot_curves(runs, cmd.x)
    table = results_table(summarize(runs))
    note = (
        "Final return: mean ± std over seeds (population std) of each seed's last evaluation. "
        "Best return: mean over seeds of each seed's best evaluation. "
        "A step is one action, held for `action repeat` frames. "
        "Paper: approximate final return at 1M steps without action repeat (1M frames) read off the "
        "reference's figure: compare it with a run's last frame, not its last step.\n"
    )
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_whole(out, {
            "curves.png": lambda path: fig.savefig(path, format="png", dpi=150),
            "curves.svg": lambda path: fig.savefig(path, format="svg"),
            "results.md": lambda path: path.write_text(f"# Results: {cmd.results}\n\n{table}\n{note}"),
        })
    except OSError as err:
        _fail(f"cannot write to {out}: {err}")
    print(table, end="")
    written = ", ".join(str(out / name) for name in ("curves.png", "curves.svg", "results.md"))
    print(f"nasa plot: {len(runs)} runs; wrote {written}")


def write_whole(out: Path, writers: dict[str, Callable[[Path], None]]) -> None:
    """Each file name in `out`, written by its writer to a temporary file first; the files replace
    the old ones only once all are written, so a full disk leaves the last plot's files whole."""
    written: list[tuple[Path, Path]] = []
    try:
        for name, write in writers.items():
            tmp = out / f".{name}.{os.getpid()}.tmp"
            written.append((tmp, out / name))
            write(tmp)
        for tmp, path in written:
            os.replace(tmp, path)
    finally:
        for tmp, _ in written:
            tmp.unlink(missing_ok=True)  # what a failed write left: free the space it took


def _fail(message: str) -> NoReturn:
    print(f"nasa plot: error: {message}", file=sys.stderr)
    sys.exit(2)
