"""The thin shell every service shares: typed flags with presets, stop signals, logging, bad messages.

Each service (`python -m services.<role>`) is configured by flags (a
`TrainConfig` under the same names as `nasa train`, with a preset) and by
environment variables for what a deployment sets per host: NASA_ZENOH_CONNECT
and NASA_RUN_ID. The defaults of every config flag are shared.config's; this
module only chooses which of them apply (--preset, --algo, --device first).

`--run-config FILE` (a run's config.json, which `nasa up` writes and passes to
every service it starts) makes that file's config the service's: config flags
given as well must agree with it, or the service refuses (ConfigMismatch, exit 2).
Services started with flags alone (deploy/docker-compose.yml) must all get the
same ones; the replay checks them against its run folder, the others against
the replay (shared.run_config).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import io
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import tyro

from shared import wire
from shared.config import (
    DEFAULT_PRESET,
    PRESET_NAMES,
    ConfigError,
    TrainConfig,
    auto_preset,
    check_types,
    default_config,
    from_dict,
    inert_flags,
    to_dict,
    validate,
)

T = TypeVar("T")

# A service ending with this code failed on its input (flags, device, task name,
# checkpoint): restarting it would fail the same way, so `nasa up` does not.
EXIT_BAD_INPUT = 2
# A service ending with this code found the Zenoh router up but refusing its login (its password or
# TLS certificate is not the router's): restarted with the same credentials it would be refused
# again, so `nasa up`, whose router and credentials are the run's, stops the run instead.
EXIT_LOGIN_REFUSED = 3


def bad_input_errors() -> tuple[type[Exception], ...]:
    """The errors that mean the user's input is wrong, not that something crashed.

    ConfigError covers shared.run_config.ConfigMismatch (settings that differ from the
    run's); StoreFormatError is a replay folder this config or version cannot open; AuthError an auth
    folder without this role's credential.
    """
    from shared.checkpoint import CheckpointError  # torch: imported only when needed
    from shared.device import DeviceError
    from shared.envs import UnknownTaskError
    from shared.replay.log import StoreFormatError
    from shared.zenoh_auth import AuthError

    return (ConfigError, DeviceError, UnknownTaskError, CheckpointError, StoreFormatError, AuthError)


class FlagError(ConfigError):
    """A command line its parser refuses (an unknown flag, a value of the wrong type, a flag
    without its value), said in one line."""


def read_flags(cls: type[T], argv: list[str], prog: str, default: T | None = None) -> T:
    """tyro.cli of `cls` on `argv`. What tyro refuses is a FlagError of one line (its reason, and
    the flag it takes to be meant where it offers one), not its box of help text; --help and
    warnings are printed as tyro prints them."""
    said = io.StringIO()
    refused = False
    try:
        with contextlib.redirect_stderr(said):
            return tyro.cli(cls, args=argv, default=default, prog=prog)
    except SystemExit as err:
        refused = bool(err.code)
        if refused:
            raise FlagError(_one_line(said.getvalue(), prog)) from None
        raise
    finally:
        if not refused:
            sys.stderr.write(said.getvalue())


def _one_line(box: str, prog: str) -> str:
    """tyro's box of an error in one line: its first section (the reason), and the first flag under
    "Perhaps you meant:" where it has one. The box's first line is its title; its borders and the
    rules between its sections are drawn or not, in Unicode or ASCII, as the output allows."""
    lines = [line.strip() for line in box.splitlines()]
    title = next((i for i, line in enumerate(lines) if line), len(lines))
    sections: list[list[str]] = [[]]
    for line in lines[title + 1 :]:
        text = line.strip("│|").strip()
        if text.strip("─-╭╮╰╯+"):
            sections[-1].append(text)
        elif sections[-1]:  # a border, or a rule between two sections
            sections.append([])
    sections = [section for section in sections if section]
    why = " ".join(sections[0]) if sections else "refused"
    meant = next((section for section in sections if section[0].startswith("Perhaps you meant")), [])
    flag = next((text.split()[0].rstrip(",") for text in meant[1:] if text.startswith("-")), None)
    return f"{why}{f'; did you mean {flag}?' if flag else ''} (`{prog} --help` lists its flags)"


def known_flags(parser: argparse.ArgumentParser, argv: list[str], prog: str) -> argparse.Namespace:
    """The flags of `parser` (made with exit_on_error=False) that `argv` gives, read before its full
    parse; one given without its value is a FlagError of one line, not argparse's usage."""
    try:
        return parser.parse_known_args(argv)[0]
    except argparse.ArgumentError as err:
        raise FlagError(f"{err} (`{prog} --help` lists its flags)") from None


def given_flags(argv: list[str]) -> set[str]:
    """The flags on a command line as tyro reads them: `--flag=VALUE` and `--flag_name` are
    `--flag` and `--flag-name`."""
    return {a.split("=", 1)[0].replace("_", "-") for a in argv if a.startswith("--")}


def parse(cls: type[T], argv: list[str] | None, prog: str) -> tuple[T, str]:
    """Parse a service's dataclass (fields `config` and `preset`); returns it and the preset used."""
    die_with_parent()
    return parse_with_preset(cls, sys.argv[1:] if argv is None else argv, prog)


def parse_with_preset(
    cls: type[T], argv: list[str], prog: str, base: TrainConfig | None = None
) -> tuple[T, str]:
    """Parse a dataclass with fields `config` and `preset`; returns it and the preset used.

    --preset, --algo, --device and --task are read first: they choose the defaults (shared.config's
    preset and its variant for the task) every other flag overrides. With `base` (a run's
    config), or when `cls` has a `run_config` field and --run-config FILE is given, that config
    is the default instead, and the preset returned is "run".
    """
    defaults = TrainConfig()
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    pre.add_argument("--preset", default=DEFAULT_PRESET)
    pre.add_argument("--algo", default=defaults.algo)
    pre.add_argument("--device", default=defaults.device)
    pre.add_argument("--run-config", type=Path, default=None)
    pre.add_argument("--task", default=None)  # a preset may have a variant for it
    known = known_flags(pre, argv, prog)
    if known.preset not in PRESET_NAMES:
        raise ConfigError(f"unknown preset {known.preset!r}; choose one of {', '.join(PRESET_NAMES)}")
    run_file = known.run_config if _has_field(cls, "run_config") else None
    if run_file is not None:
        if "--preset" in given_flags(argv):  # the run's settings are the defaults, not a preset's
            raise ConfigError(f"--preset {known.preset} with --run-config {run_file}: the run's "
                              "config.json holds its settings; leave --preset out")
        base = _read_run_config(run_file)
    if base is not None:
        check_types(base)  # before tyro, which warns of a default of another type
        preset, config = "run", from_dict(to_dict(base))
    else:
        preset = known.preset
        if preset == "auto":
            # Only the device's type matters here; do not import torch for --help.
            preset = auto_preset(_device_type(known.device))
        config = default_config(known.algo, preset, known.task)
    default = cls(config=config, preset=known.preset)  # type: ignore[call-arg]
    args = read_flags(cls, argv, prog, default)
    validate(args.config)  # type: ignore[attr-defined]
    for line in inert_flags(args.config.algo, given_flags(argv)):  # type: ignore[attr-defined]
        print(f"{prog}: note: {line}", file=sys.stderr)
    if run_file is not None:
        from shared.run_config import check_same

        check_same(args.config, base, f"--run-config {run_file}")  # type: ignore[attr-defined,arg-type]
    return args, preset


def _has_field(cls: type, name: str) -> bool:
    return any(f.name == name for f in dataclasses.fields(cls))  # type: ignore[arg-type]


def _read_run_config(path: Path) -> TrainConfig:
    from shared.run_config import read_config

    return read_config(path)


def followed(base: Mapping[str, str] = os.environ) -> dict[str, str]:
    """`base` (this process's environment) naming this process in NASA_PARENT_PID: a process started
    with it that calls `die_with_parent` (`nasa up`, `nasa train`, every service) gets SIGTERM when
    this process dies, even by SIGKILL, and stops in order."""
    return {**base, "NASA_PARENT_PID": str(os.getpid())}


def die_with_parent() -> None:
    """Under a launcher (NASA_PARENT_PID set): get SIGTERM when it dies, so no process is left (Linux)."""
    parent = os.environ.get("NASA_PARENT_PID")
    if not parent:
        return
    if not parent.isdigit():
        _stop_at_start(f"NASA_PARENT_PID={parent!r} names no process")
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        return
    if os.getppid() != int(parent):  # the launcher died before prctl took effect
        _stop_at_start(f"its launcher (pid {parent}, NASA_PARENT_PID) is not its parent process: it has "
                       "exited, or another program started this one")


def _stop_at_start(why: str) -> None:
    """Exit 1 with one line: a launcher reading the output learns why, a user who set the variable too."""
    print(f"not started: {why}", file=sys.stderr, flush=True)
    sys.exit(1)


def _device_type(name: str) -> str:
    if name.startswith("cuda"):
        return "cuda"
    if name == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return "cpu"


class StopFlag:
    """Set by SIGINT/SIGTERM or by a Stop message; services poll it or wait on it."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reason = ""
        self.signum = 0

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)

    def install_signal_handlers(self, forced: str = "") -> None:
        """SIGINT and SIGTERM set the flag. With `forced` (the line to say), a Ctrl-C after a first
        signal ends the process at once, 128 + SIGINT: a user who will not wait for the stop. Only
        a Ctrl-C: a second SIGTERM comes from a launcher (PR_SET_PDEATHSIG once `nasa up` is gone),
        which leaves the stop to take its course."""

        def handler(signum: int, _frame: object) -> None:
            if forced and signum == signal.SIGINT and self.signum:
                with contextlib.suppress(OSError):  # unbuffered: safe in a handler
                    os.write(2, f"{forced} (SIGINT)\n".encode())
                os._exit(128 + signum)
            if not self.event.is_set():
                self.signum = signum
            self.set(signal.Signals(signum).name)

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)

    def exit_if_signalled(self) -> None:
        """Exit 128 + the signal's number (the shell's convention) when a signal stopped the service:
        a supervisor then tells "stopped from outside" (restart it) from "the run is done" (exit 0)."""
        if self.signum:
            sys.exit(128 + self.signum)


class Log:
    """One line per event on stderr, flushed: time, run id, service, actor id and the message.

    Plain text by default (`2026-01-02T03:04:05.678Z [actor 1] run=r msg`); JSON lines
    (`{"time", "run_id", "service", "actor_id", "msg"}`) when NASA_LOG_JSON=1, for a log
    collector. `Log("actor 3")` is the actor service with actor id 3. Repeated warnings are
    rate limited with `every`.
    """

    def __init__(self, role: str, actor_id: int | None = None) -> None:
        name, _, ident = role.partition(" ")
        if actor_id is None and name == "actor" and ident.isdigit():
            role, actor_id = name, int(ident)
        self.role, self.actor_id = role, actor_id
        self.run_id = os.environ.get("NASA_RUN_ID", "default")
        self.json = os.environ.get("NASA_LOG_JSON", "") not in ("", "0")
        self._last: dict[str, float] = {}

    def line(self, msg: str) -> str:
        """The line one event is logged as."""
        now = time.time()
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(now)) + f".{int(now % 1 * 1000):03d}Z"
        if self.json:
            return json.dumps({"time": stamp, "run_id": self.run_id, "service": self.role,
                               "actor_id": self.actor_id, "msg": msg})
        who = self.role if self.actor_id is None else f"{self.role} {self.actor_id}"
        return f"{stamp} [{who}] run={self.run_id} {msg}"

    def __call__(self, msg: str) -> None:
        print(self.line(msg), file=sys.stderr, flush=True)

    def every(self, key: str, seconds: float, msg: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= seconds:
            self._last[key] = now
            self(msg)


class MessageGuard:
    """What a service does with a message it cannot use, and with the run's stop message.

    A bad message is counted (`invalid`) and logged, one line every 5 s at most, and the service
    goes on: no message ends a Zenoh callback with an exception. Needs `log` and `stop`."""

    invalid: int = 0
    log: Log
    stop: StopFlag

    def _invalid(self, what: str) -> None:
        self.invalid += 1
        self.log.every("invalid", 5.0, f"invalid message ({self.invalid} so far): {what}")

    def _on_stop(self, sample) -> None:  # noqa: ANN001 -- a zenoh.Sample
        try:
            self.stop.set("stop message: " + wire.decode(sample.payload.to_bytes(), wire.Stop).reason)
        except Exception as err:  # noqa: BLE001
            self._invalid(f"stop: {err}")


def _raise_interrupt(signum: int, _frame: object) -> None:
    """SIGTERM as Ctrl-C is by default: a KeyboardInterrupt where the main thread is (with its signal)."""
    raise KeyboardInterrupt(signum)


def run_service(
    cls: type[T], argv: list[str] | None, prog: str, run: Callable[[T, object, StopFlag], None],
    check: Callable[[T], None] | None = None,
) -> None:
    """A service's main: parse its flags, `check` them (a bad value is refused before the service
    connects, so it is the first error even with no router), stop on SIGINT/SIGTERM, run it on a
    client session."""
    from shared.zenoh_session import RouterUnreachable, SessionRefused, open_client  # zenoh only for services

    try:
        args, _ = parse(cls, argv, prog)
        if check is not None:
            check(args)
        role = prog.rsplit(".", 1)[-1]  # "python -m services.<role>": its Zenoh login under auth
        # open_client retries for up to 30 s where no router answers: a stop signal meanwhile ends
        # the service there, rather than once the retries give up.
        signal.signal(signal.SIGTERM, _raise_interrupt)
        try:
            session = open_client(args.connect, role=role)  # type: ignore[attr-defined]
        except KeyboardInterrupt as err:
            signum = err.args[0] if err.args else signal.SIGINT
            print(f"{prog}: stopped ({signal.Signals(signum).name}) before it connected", file=sys.stderr,
                  flush=True)
            sys.exit(128 + signum)
        stop = StopFlag()
        # Not for a robot bridge (its own main), which turns its torque off as it stops.
        stop.install_signal_handlers(forced=f"{prog}: forced to stop")
        with session:
            run(args, session, stop)
        stop.exit_if_signalled()
    except bad_input_errors() as err:
        print(f"{prog}: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_BAD_INPUT)
    except SessionRefused as err:
        print(f"{prog}: error: {err}", file=sys.stderr, flush=True)
        sys.exit(EXIT_LOGIN_REFUSED)
    except RouterUnreachable as err:  # not the input's fault: exit 1, so a supervisor retries
        print(f"{prog}: error: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
