"""`nasa reproduce`: the paper's protocol (tasks x algorithms x seeds) as one resumable command.

Each task/algo/seed is one `nasa train` subprocess writing RESULTS/<task>/<algo>/seed<S>.
Planning is a pure function of what the results folder holds (`plan_runs`), so
running the command again after an interruption continues where it stopped:

- skip:   eval.csv's last step reaches the run's step total, and train.csv holds the episode
          that ended there (finished; `run_state`);
- resume: the folder holds a started run (config.json or checkpoint.pt) that is not finished;
- start:  nothing there yet.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Literal

from shared.config import ALGOS, PRESETS, ConfigError, TrainConfig, check_algo, check_types
from shared.envs import PAPER_TASKS, check_camera, check_task
from shared.files import last_line
from shared.run_config import (
    RESUME_MAY_CHANGE,
    differences,
    differing_fields,
    read_config,
    read_json_object,
    run_flags,
)
from shared.runlog import checkpointed_step, read_rows
from shared.service import EXIT_BAD_INPUT, FlagError, followed, given_flags, read_flags

if TYPE_CHECKING:
    import torch

    from nasa.cli import TrainCommand

Action = Literal["start", "resume", "skip"]
CUDA_PARALLEL = 4
"""Default runs at a time on a GPU: the paper-scale agent leaves most of one GPU idle
(env stepping and rendering are on the CPU), so a few runs share it well."""


@dataclass(frozen=True)
class Run:
    task: str
    algo: str
    seed: int
    out: Path
    action: Action


def run_folder(results_dir: Path, task: str, algo: str, seed: int) -> Path:
    return Path(results_dir) / task / algo / f"seed{seed}"


def last_eval_step(out: Path) -> int | None:
    """The step of the last whole row of `out`/eval.csv, or None when there is none. A last row
    cut short is not a finished evaluation: the run is resumed, which drops it."""
    path = out / "eval.csv"
    if not path.exists():
        return None
    rows = read_rows(path, whole=True)
    return int(float(rows[-1]["step"])) if rows else None


def last_episode(out: Path) -> tuple[int, int] | None:
    """The step and length of the last whole row of `out`/train.csv (the last episode recorded),
    or None when there is none."""
    path = out / "train.csv"
    rows = read_rows(path, whole=True) if path.exists() else []
    return (int(float(rows[-1]["step"])), int(float(rows[-1]["length"]))) if rows else None


def run_state(out: Path, steps: int | None) -> Action:
    """What to do with one run folder. `steps` is the wanted total (None: the run's own).

    Finished means: its eval.csv holds an evaluation at the wanted total, at most the run's own
    (`nasa train` evaluates nowhere past it, and --steps rewrites it), and its train.csv holds the
    episode that ended there. The runner writes the final evaluation, then that episode's row, then
    the checkpoint; a run killed in between has its results short of their last row."""
    config_path = out / "config.json"
    started = config_path.exists() or (out / "checkpoint.pt").exists()
    if not started:
        return "start"
    try:
        own = int(read_json_object(config_path)["steps"])
        total = steps if steps is not None else own
        last = last_eval_step(out)
        episode = last_episode(out)
    except (OSError, ValueError, KeyError, TypeError, IndexError, OverflowError):  # Overflow: inf
        # A damaged or missing config.json, or rows it cannot read: `nasa train --resume` names
        # what is wrong, and that run fails alone.
        return "resume"
    # An episode that ended by the final evaluation's step with no row: killed before writing it.
    # A step past its own total is a damaged row.
    if last is not None and total <= last <= own and (episode is None or sum(episode) > last):
        return "skip"
    # A config.json without a checkpoint is a run killed before its first checkpoint;
    # `nasa train --resume` starts it over in place (a fresh start would refuse the folder).
    return "resume"


def lost_checkpoint(out: Path) -> str | None:
    """Why the run in `out` had a checkpoint that is gone, or None. A run is checkpointed at the end
    of its first episode past checkpoint_every steps; a train.csv row after that episode's means the
    checkpoint was written. Without it, `nasa train --resume` starts the run over, as one killed
    before its first checkpoint, and clears the rows it holds."""
    if (out / "checkpoint.pt").exists() or not (out / "train.csv").exists():
        return None
    try:
        every = int(read_json_object(out / "config.json")["checkpoint_every"])
    except (OSError, ValueError, KeyError, TypeError, OverflowError):
        return None  # a damaged file: `nasa train --resume` names it
    if (saved := checkpointed_step(out, every)) is None:
        return None
    return f"no checkpoint.pt, though its train.csv goes on past the one saved at step {saved}"


def plan_runs(
    results_dir: Path, tasks: list[str], algos: list[str], seeds: list[int], steps: int | None
) -> list[Run]:
    """One Run per task/algo/seed with what to do with it; reads the folders, changes nothing."""
    runs = []
    for task in tasks:
        for algo in algos:
            for seed in seeds:
                out = run_folder(results_dir, task, algo, seed)
                runs.append(Run(task, algo, seed, out, run_state(out, steps)))
    return runs


class DamagedConfig(ConfigError):
    """A run folder's config.json that cannot be read as a run's settings."""


def settings_mismatch(run: Run, preset: str, device: str, extra: list[str]) -> tuple[str, list[str]] | None:
    """Why the run already in `run.out` is not the one this command would start there (another
    preset, flags, task, algorithm or seed: each differing setting with both values), and the flags
    that give the run's settings back; None when it is. The step budget and the device may differ:
    a resumed run keeps its own device, and --steps extends it. DamagedConfig, naming the file and
    what is wrong with it, if its config.json holds no settings (unreadable, or a value of the
    wrong type): compared, each such value would read as a setting of its own."""
    from nasa.cli import parse_train

    path = run.out / "config.json"
    if not path.exists():
        return None  # a checkpoint alone: `nasa train --resume` names what is missing
    try:
        saved = read_config(path)
        check_types(saved)
    except ConfigError as err:
        where = "" if str(path) in str(err) else f"{path}: "
        raise DamagedConfig(f"{where}{err}") from err
    wanted, _, _ = parse_train(start_args(run, preset, device, None, extra))
    fields = differing_fields(wanted.config, saved, ignore=("steps", "device", *RESUME_MAY_CHANGE))
    return (differences(fields, wanted.config, saved), run_flags(fields, saved)) if fields else None


def train_command(
    run: Run, preset: str, device: str, steps: int | None, extra: list[str]
) -> list[str]:
    """The `nasa train` command line of one run (start or resume)."""
    base = [sys.executable, "-m", "nasa.cli", "train"]
    steps_flag = ["--steps", str(steps)] if steps is not None else []
    if run.action == "resume":
        # A resumed run keeps the settings in its config.json; only --steps changes it.
        return [*base, "--resume", str(run.out), *steps_flag]
    if run.action != "start":
        raise ValueError(f"run {run.out} is to be skipped, it has no command")
    return [*base, *start_args(run, preset, device, steps, extra)]


def start_args(run: Run, preset: str, device: str, steps: int | None, extra: list[str]) -> list[str]:
    """`nasa train`'s flags that start `run` in its folder."""
    steps_flag = ["--steps", str(steps)] if steps is not None else []
    return ["--algo", run.algo, "--task", run.task, "--seed", str(run.seed), "--out", str(run.out),
            "--preset", preset, "--device", device, *steps_flag, *extra]


def execute(jobs: list[tuple[Run, list[str]]], parallel: int, poll_s: float = 1.0) -> list[Run]:
    """Run the commands, at most `parallel` at a time; each run's output goes to <out>/train.log.

    Returns the runs whose process failed. A failed run does not stop the others:
    the next `nasa reproduce` resumes it. Whatever ends this loop early (Ctrl-C, SIGTERM) stops
    the runs under way and waits for them, so none is left running on its own.
    """
    pending = list(jobs)
    running: list[tuple[Run, subprocess.Popen, object]] = []
    failed: list[Run] = []
    try:
        while pending or running:
            while pending and len(running) < parallel:
                run, cmd = pending.pop(0)
                try:
                    proc, log = launch(run, cmd)
                except OSError as err:  # its folder cannot be written: this run fails, not the others
                    failed.append(run)
                    where = f" ({err.filename})" if err.filename else ""
                    print(f"FAILED {run.out}: cannot start it: {err.strerror or err}{where}", flush=True)
                    continue
                running.append((run, proc, log))
                print(f"{run.action:6s} {run.out} (log {run.out / 'train.log'})", flush=True)
            for item in list(running):
                run, proc, log = item
                code = proc.poll()
                if code is None:
                    continue
                running.remove(item)
                log.close()
                if code == 0:
                    print(f"done   {run.out}", flush=True)
                elif code == EXIT_BAD_INPUT:
                    failed.append(run)
                    print(f"FAILED {run.out}: exit code {code}, it refused its input "
                          f"({log_error(run.out / 'train.log')}); running it again fails the same way "
                          "until that is fixed", flush=True)
                else:
                    failed.append(run)
                    print(f"FAILED {run.out}: exit code {code}, see {run.out / 'train.log'}", flush=True)
            if running:
                time.sleep(poll_s)
    except BaseException:
        # Stop our own children and wait for them; the next invocation resumes them. A second
        # Ctrl-C or SIGTERM during the wait kills them (a run stopping slowly, or stuck), never
        # leaving one running on its own.
        from nasa.stopping import STOP_SIGNALS, second_signal_forces

        def kill_left() -> str:
            left = [proc for _, proc, _log in running if proc.poll() is None]
            for proc in left:
                proc.kill()
            return f"{len(left)} run(s) under way killed" if left else ""

        handlers = {s: signal.getsignal(s) for s in STOP_SIGNALS}
        second_signal_forces("nasa reproduce", "run the same command again to resume them", kill_left)
        try:
            for _, proc, _log in running:
                proc.terminate()
            for _, proc, log in running:
                proc.wait()
                log.close()
        finally:
            for signum, handler in handlers.items():
                signal.signal(signum, handler)
        raise
    return failed


def log_error(path: Path) -> str:
    """The last line of a run's train.log (its error, when `nasa train` refused its input)."""
    try:
        line = last_line(path)
    except OSError as err:
        return f"{path} cannot be read: {err.strerror or err}"
    return line or f"{path} is empty"


def run_until_stopped(jobs: list[tuple[Run, list[str]]], parallel: int) -> list[Run]:
    """`execute`; on Ctrl-C (SIGINT) or SIGTERM, once the runs under way have stopped, say how to
    go on in one line and exit 128 + the signal (130, 143), the shell's convention."""
    from nasa.stopping import Terminated, ignore_stop_signals, raise_terminated, signal_code

    signal.signal(signal.SIGTERM, raise_terminated)
    try:
        return execute(jobs, parallel)
    except (KeyboardInterrupt, Terminated) as err:
        ignore_stop_signals()
        print("\nnasa reproduce: stopped, and so were the runs under way; run the same command "
              "again to resume them", file=sys.stderr, flush=True)
        sys.exit(signal_code(err))


def launch(run: Run, cmd: list[str]) -> tuple[subprocess.Popen, IO[str]]:
    """Start `cmd` with its output going to <out>/train.log; returns the process and the log,
    to be closed when the run ends. The run gets SIGTERM should this process die, even by SIGKILL
    (NASA_PARENT_PID: shared.service.die_with_parent): left running, it would hold its folder, and
    the `nasa reproduce` started again to resume it would find it taken."""
    run.out.mkdir(parents=True, exist_ok=True)
    log = open(run.out / "train.log", "a")
    try:
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=followed()), log
    except BaseException:
        log.close()
        raise


@dataclass
class ReproduceCommand:
    """Run the paper's protocol: every task x algo x seed, one `nasa train` each, resumable.

    Run it again after an interruption: finished runs are skipped, started ones
    resumed from their checkpoint. Flags after `--` go to each new `nasa train`.
    """

    tasks: str = "paper"
    """`paper` (the six tasks of the paper) or a comma list of tasks (e.g. cheetah-run,walker-walk)."""
    algos: str = ",".join(ALGOS)
    """Comma list of algorithms."""
    seeds: int = 5
    """Number of seeds: 5 means seeds 0..4."""
    results: Path = Path("results")
    """Results folder; each run goes to RESULTS/<task>/<algo>/seed<S>."""
    steps: int | None = None
    """Env steps per run (default: the preset's, 1M for paper). Finished means the last
    evaluation reached this step, so use a multiple of the evaluation interval."""
    preset: str = "paper"
    """Settings preset of new runs: `paper` (the reference's) or `cpu-small`."""
    device: str = TrainConfig.device
    """Device for new runs (a resumed run keeps its config.json's)."""
    parallel: int | None = None
    """Runs at a time (default: 1 on a CPU, 4 on CUDA)."""
    dry_run: bool = False
    """Print the plan (start / resume / skip per run) and start nothing."""


# Each run's own flags (and --steps, which planning reads): after `--` they would override them.
RUN_FLAGS = ("--seed", "--task", "--algo", "--out", "--preset", "--device", "--resume", "--steps")


def check_extra(extra: list[str], tasks: list[str], probe: Run, preset: str, device: str,
                steps: int | None) -> None:
    """Refuse flags after `--` that would override a run's own, then parse one run's full
    `nasa train` command line as `nasa train` does, and check a --camera-id against each task:
    a bad value is one error here, not one failed run per task, algorithm and seed."""
    clashes = [flag for flag in RUN_FLAGS if flag in given_flags(extra)]
    if clashes:
        raise ConfigError(
            f"{', '.join(clashes)} after -- would override what nasa reproduce sets for each run; "
            "use nasa reproduce's --tasks, --algos, --seeds, --results, --preset, --device and --steps")
    wanted = parse_quietly(start_args(probe, preset, device, steps, extra))
    if "--camera-id" in given_flags(extra):
        for task in tasks:
            check_camera(dataclasses.replace(wanted.config.env, task=task))


def parse_quietly(argv: list[str]) -> TrainCommand:
    """`nasa train`'s parse of `argv`; what its parser refuses (an unknown flag, a value of the
    wrong type) is one line naming what comes after --."""
    from nasa.cli import parse_train

    try:
        return parse_train(argv)[0]
    except FlagError as err:
        raise ConfigError(f"after --: {err}") from None


def parse_list(text: str) -> list[str]:
    """A comma list without blanks or repeats, in the order given."""
    return list(dict.fromkeys(item.strip() for item in text.split(",") if item.strip()))


def reproduce(argv: list[str]) -> None:
    """`nasa reproduce`; a Ctrl-C before any run is under way (while it checks its flags, imports
    torch or plans) stops it with one line, exit 130, as one while the runs are under way does."""
    try:
        checked_and_run(argv)
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second one would cut the line short
        print("\nnasa reproduce: stopped before any run was under way", file=sys.stderr, flush=True)
        sys.exit(128 + signal.SIGINT)


def checked_and_run(argv: list[str]) -> None:
    argv, extra = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else (argv, [])
    cmd = read_flags(ReproduceCommand, argv, "nasa reproduce")
    tasks = list(PAPER_TASKS) if cmd.tasks == "paper" else parse_list(cmd.tasks)
    algos = parse_list(cmd.algos)
    if not tasks or not algos:
        raise ConfigError("--tasks and --algos must each name at least one")
    for task in tasks:
        check_task(task)  # UnknownTaskError lists the valid names of every environment source
    for algo in algos:
        check_algo(algo)
    if cmd.preset not in PRESETS:
        raise ConfigError(f"unknown preset {cmd.preset!r}; choose one of {', '.join(PRESETS)}")
    if cmd.seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {cmd.seeds}")
    if cmd.steps is not None and cmd.steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {cmd.steps}")
    if cmd.parallel is not None and cmd.parallel < 1:
        raise ConfigError(f"--parallel must be >= 1, got {cmd.parallel}")
    probe = Run(tasks[0], algos[0], 0, run_folder(cmd.results, tasks[0], algos[0], 0), "start")
    check_extra(extra, tasks, probe, cmd.preset, cmd.device, cmd.steps)
    from shared.device import resolve_device  # imports torch: after the cheap checks

    device = resolve_device(cmd.device)
    parallel = cmd.parallel if cmd.parallel is not None else CUDA_PARALLEL if device.type == "cuda" else 1

    if cmd.results.exists() and not cmd.results.is_dir():
        raise ConfigError(f"--results {cmd.results} is a file, not a folder")
    if cmd.dry_run:
        plan_and_run(cmd, tasks, algos, extra, device, parallel)
        return
    with lock_runs(cmd.results, [(t, a, seed) for t in tasks for a in algos for seed in range(cmd.seeds)]):
        plan_and_run(cmd, tasks, algos, extra, device, parallel)


SPARE_FILES = 256
"""Open files a `nasa reproduce` keeps for itself beside its runs' locks (logs, its children's pipes)."""


def open_files_for(locks: int) -> None:
    """Raise this process's soft limit of open files to fit a lock per run (each holds one open)
    and SPARE_FILES more, up to its hard limit; ConfigError if even that is too few."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = locks + SPARE_FILES
    if soft == resource.RLIM_INFINITY or needed <= soft:
        return
    if hard != resource.RLIM_INFINITY and needed > hard:
        raise ConfigError(f"{locks} runs need {needed} open files (a lock each), over this process's "
                          f"limit of {hard} (ulimit -Hn): give fewer --tasks, --algos or --seeds at a time")
    resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


LOCKS_DIR = ".reproduce"
"""Under the results folder: one lock folder per run, RESULTS/.reproduce/<task>/<algo>/seed<S>."""


@contextlib.contextmanager
def lock_runs(results: Path, runs: list[tuple[str, str, int]]) -> Iterator[None]:
    """Hold a lock for each run of this `nasa reproduce` while it plans and runs them. A second one
    given any of these runs would start the runs the first has under way, see their folders refuse
    them, and report them failed: it is refused; one with other runs of the same results folder
    (other tasks, algorithms or seeds) goes on beside it. The locks live beside the run folders,
    not in them: `nasa train` takes its own folder's lock, and waits for any other one there."""
    from shared.faults import RunFolderError, RunHeld, lock_run, owner

    open_files_for(len(runs))
    held = []
    try:
        for task, algo, seed in runs:
            where = run_folder(Path(results) / LOCKS_DIR, task, algo, seed)
            try:
                held.append(lock_run(where, "nasa reproduce", "--results"))
            except RunHeld as err:  # any other RunFolderError (it cannot be written) says so itself
                raise RunFolderError(
                    f"{run_folder(results, task, algo, seed)} is a run of another nasa reproduce "
                    f"({owner(where)}); stop that one, or give this one other --tasks, --algos or "
                    "--seeds") from err
        yield
    finally:
        for lock in held:
            lock.close()


def plan_and_run(cmd: ReproduceCommand, tasks: list[str], algos: list[str], extra: list[str],
                 device: torch.device, parallel: int) -> None:
    """Plan the runs from what `cmd.results` holds, then print the plan (a dry run) or run it."""
    runs = plan_runs(cmd.results, tasks, algos, list(range(cmd.seeds)), cmd.steps)
    # A folder holding a run of other settings would be resumed, or counted finished, as this one.
    mismatched, damaged = [], []
    for r in runs:
        if r.action == "start":
            continue
        try:
            if why := settings_mismatch(r, cmd.preset, cmd.device, extra):
                mismatched.append((r, why))
        except DamagedConfig as err:
            damaged.append(str(err))
    if damaged:
        more = f" (and {len(damaged) - 3} more)" if len(damaged) > 3 else ""
        raise ConfigError(
            f"--results {cmd.results} holds runs whose config.json is damaged: {'; '.join(damaged[:3])}"
            f"{more}. Fix the file, or move the run's folder aside to run it again")
    if mismatched:
        shown = "; ".join(f"{r.out}: {why}" for r, (why, _) in mismatched[:3])
        more = f" (and {len(mismatched) - 3} more)" if len(mismatched) > 3 else ""
        # A default changed since the runs began (an upgrade) is the usual cause: these flags after
        # -- continue them, and give the runs still to start the same settings. A run's own (its
        # seed: a folder moved by hand) cannot be given there.
        flags = " ".join(dict.fromkeys(f for _, (_, fs) in mismatched for f in fs
                                       if f.split()[0] not in RUN_FLAGS))
        add = f" (add after --: {flags})" if flags else ""
        raise ConfigError(
            f"--results {cmd.results} holds runs made with other settings than --preset {cmd.preset} "
            f"and the flags after -- give: {shown}{more}. Use the settings they were made with{add}, "
            "or another --results folder")
    lost = [(r, why) for r in runs if r.action == "resume" and (why := lost_checkpoint(r.out))]
    if lost:
        shown = "; ".join(f"{r.out}: {why}" for r, why in lost[:3])
        more = f" (and {len(lost) - 3} more)" if len(lost) > 3 else ""
        raise ConfigError(
            f"--results {cmd.results} holds runs whose checkpoint.pt is gone: {shown}{more}. Resumed, "
            "each would start over and erase its eval.csv and train.csv; put its checkpoint.pt back, "
            "or move the folder aside to run it again")
    counts = {a: sum(r.action == a for r in runs) for a in ("start", "resume", "skip")}
    print(
        f"nasa reproduce: {len(runs)} runs ({len(tasks)} tasks x {len(algos)} algos x {cmd.seeds} seeds) "
        f"in {cmd.results}: {counts['start']} to start, {counts['resume']} to resume, "
        f"{counts['skip']} finished; preset {cmd.preset}, device {device}, {parallel} at a time",
        flush=True,
    )
    todo = [r for r in runs if r.action != "skip"]
    jobs = [(r, train_command(r, cmd.preset, cmd.device, cmd.steps, extra)) for r in todo]
    if cmd.dry_run:
        commands = {run.out: command for run, command in jobs}
        for run in runs:
            print(f"{run.action:6s} {run.task} {run.algo} seed {run.seed} -> {run.out}")
            if run.out in commands:
                print("       " + shlex.join(["nasa", *commands[run.out][3:]]))
        return
    if extra and counts["resume"]:
        print("note: flags after -- apply to new runs only; resumed runs keep their config.json", flush=True)
    failed = run_until_stopped(jobs, parallel)
    # A run whose process ended well is finished only if its eval.csv says so: a final evaluation
    # that failed, or a final row since lost, would otherwise be "all runs finished" here and
    # resumed again by every later plan.
    unfinished = [r for r in todo if r not in failed and run_state(r.out, cmd.steps) != "skip"]
    for run in unfinished:
        print(f"UNFINISHED {run.out}: its `nasa train` ended, but its eval.csv holds no evaluation at "
              f"its last step, or its train.csv not the episode that ended there; see "
              f"{run.out / 'train.log'}", file=sys.stderr)
    if failed:
        print(f"nasa reproduce: {len(failed)} run(s) failed; run the same command again to resume them "
              "(one that refused its input, exit code 2, once what it names is fixed)", file=sys.stderr)
    if unfinished:
        print(f"nasa reproduce: {len(unfinished)} run(s) ended without an evaluation at their last step, "
              "so they are not finished", file=sys.stderr)
    if failed or unfinished:
        sys.exit(1)
    print(f"nasa reproduce: all runs finished; plot them with `nasa plot {cmd.results}`")
