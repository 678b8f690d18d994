"""`nasa`: the command line. Each subcommand is a typed dataclass read by tyro."""

from __future__ import annotations

from nasa.stopping import interrupted  # first, and light: a Ctrl-C during the imports below is one line

with interrupted("nasa", "while starting"):
    import argparse
    import contextlib
    import signal
    import sys
    from collections.abc import Callable
    from dataclasses import dataclass, field
    from pathlib import Path
    from typing import TYPE_CHECKING, Annotated

    import tyro

    from nasa.plot import plot
    from nasa.reproduce import reproduce
    from nasa.stopping import (
        STOP_SIGNALS,
        Terminated,
        ignore_stop_signals,
        raise_on_stop_signals,
        raise_terminated,
        second_signal_forces,
        shares_launchers_ctrl_c,
        signal_code,
        stop_code,
    )
    from shared import run_config
    from shared.config import DEFAULT_PRESET, ConfigError, TrainConfig
    from shared.device import resolve_device
    from shared.service import (
        EXIT_BAD_INPUT,
        bad_input_errors,
        die_with_parent,
        given_flags,
        known_flags,
        parse_with_preset,
    )

if TYPE_CHECKING:
    from nasa.train import Trainer


@dataclass
class TrainCommand:
    """Train one agent on one task in a single process."""

    config: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=TrainConfig)
    out: Path | None = None
    """Run folder (default runs/<task>-<algo>-s<seed>)."""
    resume: Path | None = None
    """Continue the run in this folder exactly from its last checkpoint, with its settings;
    --steps may set a new step budget, any other config flag must agree with the run's."""
    preset: str = DEFAULT_PRESET
    """`paper` (the reference settings), `cpu-small`, or `auto`: paper on a GPU, cpu-small on a CPU."""


def resume_folder(argv: list[str]) -> Path | None:
    """The --resume folder of a `nasa train` command line, if any (read before the full parse,
    because the run's config.json supplies the defaults)."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    pre.add_argument("--resume", type=Path, default=None)
    return known_flags(pre, argv, "nasa train").resume


def parse_train(argv: list[str]) -> tuple[TrainCommand, str, int | None]:
    """`nasa train`'s flags; returns them, the preset used, and (resuming) the new step budget or None.

    Resuming, the run's config.json is the default of every config flag, so a flag that
    is given and differs from the run's is a ConfigMismatch naming it; --steps alone may change.
    """
    folder = resume_folder(argv)
    if folder is None:
        cmd, preset = parse_with_preset(TrainCommand, argv, "nasa train")
        return cmd, preset, None
    if "--preset" in given_flags(argv):
        raise ConfigError(f"--resume {folder} with --preset: a resumed run keeps the settings in its "
                          "config.json; leave --preset out")
    path = folder / run_config.CONFIG_FILE
    if not path.exists():
        raise ConfigError(f"--resume {folder}: no run there ({path} does not exist)")
    saved = run_config.read_config(path)
    cmd, preset = parse_with_preset(TrainCommand, argv, "nasa train", base=saved)
    if cmd.out is not None and cmd.out.resolve() != folder.resolve():
        raise ConfigError(f"--resume {folder} with --out {cmd.out}: a resumed run goes on in its own "
                          "folder; leave --out out")
    # The device is compared too: Trainer.resume continues on the run's.
    fields = run_config.differing_fields(cmd.config, saved, ignore=run_config.RESUME_MAY_CHANGE)
    if fields:
        raise run_config.ConfigMismatch(str(path), fields, cmd.config, saved)
    steps = cmd.config.steps if cmd.config.steps != saved.steps else None
    return cmd, preset, steps


def train(argv: list[str]) -> None:
    die_with_parent()  # under `nasa reproduce`: stop when it dies, not go on holding the run folder
    cmd, preset, steps = parse_train(argv)
    device = resolve_device(cmd.config.device)
    from nasa.train import Trainer  # after parsing: --help needs no torch or GL
    from shared.agents import check_update_device
    from shared.faults import lock_run

    if cmd.resume is not None:
        check_update_device(cmd.config.agent, device)  # --cuda-graph may be asked for on resuming
        with lock_run(cmd.resume, "nasa train --resume"):
            print(f"nasa train: resuming {cmd.resume}", flush=True)
            trainer = open_trainer(
                lambda: Trainer.resume(cmd.resume, steps=steps, cuda_graph=cmd.config.agent.cuda_graph),
                cmd.resume)
            run_until_stopped(trainer, cmd.resume)
        return
    c = cmd.config
    from shared.envs import check_camera, check_task

    check_task(c.env.task)  # before the first line names it and before the run folder is made
    check_camera(c.env)
    check_update_device(c.agent, device)
    out = cmd.out or Path("runs") / f"{c.env.task}-{c.algo}-s{c.seed}"
    how = f"{preset} (auto: {device.type})" if cmd.preset == "auto" else preset
    print(
        f"nasa train: {c.algo} on {c.env.task}, seed {c.seed}, {c.steps} steps, "
        f"preset {how}, device {device}, out {out}",
        flush=True,
    )
    with lock_run(out, "nasa train", "--out"):
        run_until_stopped(open_trainer(lambda: Trainer.create(c, out), out), out)


def open_trainer(make: Callable[[], Trainer], out: Path) -> Trainer:
    """`make()`: the run's Trainer, made or resumed. A disk that refuses its first writes is a
    RunFolderError; a Ctrl-C or SIGTERM meanwhile (a resume reading a long replay log) stops it
    with one line, as in the run: what the folder holds is cut back again on the next resume."""
    from shared.faults import RunFolderError

    signal.signal(signal.SIGTERM, raise_terminated)
    try:
        return make()
    except OSError as err:
        raise RunFolderError(f"{out}: {write_error(err)}") from err
    except (KeyboardInterrupt, Terminated) as err:
        ignore_stop_signals()  # one line to print, then it exits
        how = (f"continue with: nasa train --resume {out}" if (out / run_config.CONFIG_FILE).exists()
               else "start it again")
        print(f"\nnasa train: stopped before the run began; {how}", file=sys.stderr, flush=True)
        sys.exit(signal_code(err))


def run_until_stopped(trainer: Trainer, out: Path) -> None:
    """Run to the step budget; on Ctrl-C (SIGINT) or SIGTERM, release the renderers, say how to
    continue, and exit 128 + the signal (130, 143), the shell's convention. A file the run cannot
    write (a full disk, a folder made read-only), or an environment that faults in episode after
    episode or at every reset, stops it the same way, with exit 1."""
    from nasa.train import EnvFaultsInARow
    from shared.envs import EnvFault

    raise_on_stop_signals()
    try:
        trainer.run()
    except (KeyboardInterrupt, Terminated) as err:
        _stopped(trainer, out, "", signal_code(err))
    except OSError as err:
        _stopped(trainer, out, f": {write_error(err)}", 1, "once it can be written again, ")
    except (EnvFaultsInARow, EnvFault) as err:  # a step's EnvFault is handled in the run: a reset's
        _stopped(trainer, out, f": {err}", 1)
    except Exception as err:
        # A stop signal whose exception a C extension replaced (it rang while a frame rendered).
        if (code := stop_code(err)) is None:
            raise
        _stopped(trainer, out, "", code)


def write_error(err: OSError) -> str:
    """An OSError in one line, naming its file where it has one."""
    where = f" ({err.filename})" if err.filename else ""
    return f"cannot write the run folder: {err.strerror or err}{where}"


def _stopped(trainer: Trainer, out: Path, why: str, code: int, when: str = "") -> None:
    saved = trainer.last_checkpoint_step
    where = (f"its last checkpoint holds step {saved}" if saved
             else "it has no checkpoint yet, so --resume starts it over")
    # Closing flushes the replay's log and TensorBoard's files: a slow disk can hold it up, and a
    # second signal then ends it at once (the checkpoint is whole, the logs drop what was cut).
    # Under `nasa reproduce`, its SIGTERM follows the terminal's Ctrl-C that both got: a stop,
    # not a second signal; the terminal's second Ctrl-C still forces. Under a launcher in another
    # session (bench.learning, whose SIGTERM follows a SIGINT that was not enough) either forces.
    ignore_stop_signals()
    forcing = (signal.SIGINT,) if shares_launchers_ctrl_c() else STOP_SIGNALS
    second_signal_forces("nasa train", f"{where}; {when}continue with: nasa train --resume {out}",
                         signals=forcing)
    signalled = code > 128
    if signalled:
        print(f"\nnasa train: stopping at step {trainer.counters.env_steps}: closing the run's files "
              "(Ctrl-C again to stop at once)", file=sys.stderr, flush=True)
    with contextlib.suppress(OSError):  # closing flushes files the disk may still refuse
        trainer.close()
    ignore_stop_signals()  # closed: one line to print, then it exits
    lead = "" if signalled else "\n"  # after the "stopping" line, or the first
    print(f"{lead}nasa train: stopped at step {trainer.counters.env_steps}{why}; "
          f"{where}; {when}continue with: nasa train --resume {out}", file=sys.stderr, flush=True)
    sys.exit(code)


def up(argv: list[str]) -> None:
    try:
        from nasa.up import up as run_up  # the launcher imports zenoh; keep `nasa train --help` light

        run_up(argv)
    except (KeyboardInterrupt, Terminated) as err:  # before nasa up's own handlers, so before any service
        how = "interrupted" if isinstance(err, KeyboardInterrupt) else "stopped (SIGTERM)"
        print(f"\nnasa up: {how} before any service started", file=sys.stderr, flush=True)
        sys.exit(signal_code(err))


def status(argv: list[str]) -> None:
    from nasa.up import status as print_status

    print_status(argv)


def auth(argv: list[str]) -> None:
    from nasa.auth import auth as run_auth

    run_auth(argv)


# Each subcommand and its line in `nasa --help`, in the order a user meets them.
COMMANDS = {
    "up": (up, "the whole system on this host, each service its own process; status at http://127.0.0.1:8000"),
    "train": (train, "one agent on one task in a single process (--resume DIR continues a run)"),
    "reproduce": (reproduce, "the paper's protocol: a `nasa train` per task, algorithm and seed, resumable"),
    "plot": (plot, "learning curves and a results table from the eval.csv files under a folder"),
    "status": (status, "a running system's /status, or a stopped run's (--data DIR; --serve: its dashboard)"),
    "auth": (auth, "Zenoh logins, access-control list and TLS certificates for a run across hosts"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items()]
    return "\n".join([f"usage: nasa {{{', '.join(COMMANDS)}}} [--help]", "", "commands:", *lines, "",
                      "`nasa COMMAND --help` lists a command's flags."])


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in COMMANDS:
        asked = bool(argv) and argv[0] in ("-h", "--help")
        if argv and not asked:
            print(f"nasa: unknown command {argv[0]!r}", file=sys.stderr)
        print(usage(), file=sys.stdout if asked else sys.stderr)
        sys.exit(0 if asked else EXIT_BAD_INPUT)
    # SIGTERM as Ctrl-C until a command sets its own stop: its default would end the process
    # without a word (and in a container, as process 1, not at all).
    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        with interrupted(f"nasa {argv[0]}"):  # a command's own stop takes over once it is set up
            COMMANDS[argv[0]][0](argv[1:])
    except (*bad_input_errors(), FileExistsError) as err:
        print(f"nasa {argv[0]}: error: {err}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    finally:
        signal.signal(signal.SIGTERM, previous)  # main() called in a process of another's (a test)


if __name__ == "__main__":
    main()
