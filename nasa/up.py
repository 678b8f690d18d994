"""`nasa up`: the whole distributed system on this host, one OS process per service.

The launcher runs the Zenoh router in its own process (a session in router
mode) and starts replay, learner, evaluator and N actors as child processes
(`python -m services.<role>`, the same commands the deployment files run). A
child that dies is restarted (a restarted actor draws a new incarnation),
unless it refused its input (exit code 2: a bad flag, device, task name,
checkpoint, replay folder or settings that differ from the run's) or the
router refused its login (exit code 3), which would only fail again.

One config per run: `nasa up` parses its config flags with the parser every
service uses (shared.service.parse_with_preset, defaults from shared.config),
checks the task through its environment source, and opens the run folder
(shared.run_config.open_folder) before starting anything: a new folder gets the
resolved config in <data>/config.json; a resumed one must have been started
with the same settings (else exit 2 naming the fields; only --steps may
change). Every service is then started with `--run-config <data>/config.json`,
so all of them run that file's settings.

With `--bridge` (gripper tasks), each actor steps its gripper through a robot
bridge process that `nasa up` starts first and supervises like the others
(`with_bridges`): the MuJoCo stand-in, the real driver on an emulated servo
bus, or the real gripper.

The run ends when the learner finishes the step budget (it publishes Stop and
every service exits), when the learner or the replay ends for good (`nasa up`
then exits non-zero: 2 if it refused its input), when the router refuses a
service's login (exit 2), on Ctrl-C, SIGTERM or SIGHUP (its terminal closed;
exit 130, 143 or 129, the shell's 128 + the signal: a run stopped from outside
is not a finished one).
Children are stopped in order (STOP_ORDER: actors, robot bridges, evaluator, learner, replay; a stop signal
while they are being started starts no more of them), killed if
they do not exit in time, or at once on a second Ctrl-C or SIGTERM (StopSignals),
and get SIGTERM if the launcher itself dies (PR_SET_PDEATHSIG, set by each
service at start), so no process is left. Started by a launcher of its own that
names itself in NASA_PARENT_PID, `nasa up` gets SIGTERM in turn
when that one dies, even by SIGKILL, and stops its services in order.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, BinaryIO, Literal

import tyro

from nasa import layout
from nasa.stopping import second_signal_forces
from shared import envs, run_config, wire
from shared.config import DEFAULT_PRESET, EVAL_SEED_OFFSET, ConfigError, TrainConfig, validate
from shared.files import last_line
from shared.run_config import RunConfig
from shared.service import (
    EXIT_BAD_INPUT,
    EXIT_LOGIN_REFUSED,
    die_with_parent,
    followed,
    given_flags,
    parse_with_preset,
    read_flags,
)
from shared.zenoh_auth import USERS_FILE

RUN_AUTH = "run"
"""--zenoh-auth's default: the run folder's own credentials."""

STOP_ORDER = ("actor", "robot_bridge", "evaluator", "learner", "replay")  # a bridge e-stops as it stops
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
FORCE_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # a closed terminal can send SIGHUP twice


def service_command(role: str) -> list[str]:
    """The command that runs one service (what the deployment files run too)."""
    return [sys.executable, "-m", f"services.{role}"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Child:
    name: str
    role: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    exited: int | None = None  # exit code once it ended for good
    pids: list[int] = field(default_factory=list)
    nice: int = 0  # added to the child's CPU niceness (lower priority)
    env: dict[str, str | None] = field(default_factory=dict)  # over the supervisor's; None: unset
    started: float = 0.0  # when its current process started (monotonic)


def child_env(base: dict[str, str], over: dict[str, str | None]) -> dict[str, str]:
    env = followed(base)
    for key, value in over.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return env


def exit_text(code: int) -> str:
    """How a child's process ended, from its return code (negative: the signal that killed it)."""
    if code >= 0:
        return f"exited with {code}"
    try:
        return f"was killed by {signal.Signals(-code).name}"
    except ValueError:
        return f"was killed by signal {-code}"


def disk_full(folder: Path) -> str:
    """"; no space is left on its disk" where `folder`'s file system has (next to) none left, else ""."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return ""
    return "; no space is left on its disk" if st.f_bavail * st.f_frsize < FULL_BELOW_BYTES else ""


FULL_BELOW_BYTES = 1 << 20
STABLE_S = 120.0
"""A child that ran this long before it died starts its count of restarts in a row again."""
MAX_RESTART_DELAY_S = 30.0


class Supervisor:
    """Starts services as child processes, restarts the ones that die, stops them all in order."""

    def __init__(self, env: dict[str, str], log_dir: Path | None, max_restarts: int = 20,
                 restart_delay_s: float = 1.0, cwd: str | None = None,
                 command: Callable[[str], list[str]] = service_command,
                 stable_s: float = STABLE_S) -> None:
        self.env = env
        self.command = command
        self.log_dir = log_dir
        self.max_restarts = max_restarts
        self.restart_delay_s = restart_delay_s
        self.stable_s = stable_s
        self.cwd = cwd
        self.children: dict[str, Child] = {}
        self.stopping = False
        self._dead_since: dict[str, float] = {}
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)

    def add(self, name: str, role: str, argv: list[str], nice: int = 0,
            env: dict[str, str | None] | None = None) -> Child:
        child = Child(name, role, argv, nice=nice, env=env or {})
        self.children[name] = child
        self._spawn(child)
        return child

    def _open_log(self, child: Child, on_event: Callable[[str], None]) -> BinaryIO | None:
        """The child's log, opened to append; None (this terminal) where it cannot be written: a
        log that fails is no reason to stop the run."""
        log = self.log_file(child)
        if log is None:
            return None
        try:
            log.parent.mkdir(parents=True, exist_ok=True)  # removed while the run went on
            return open(log, "ab")  # noqa: SIM115 (owned by the child)
        except OSError as err:
            on_event(f"{child.name}'s log {log} cannot be written ({err.strerror or err}): its output "
                     "comes here")
            return None

    def _spawn(self, child: Child, on_event: Callable[[str], None] = print) -> None:
        out = self._open_log(child, on_event)
        try:
            # `nice` execs the service in the same process, so every thread it starts inherits the priority.
            prefix = ["nice", "-n", str(child.nice)] if child.nice else []
            child.proc = subprocess.Popen(
                [*prefix, *self.command(child.role), *child.argv],
                # Each service asks for SIGTERM when this process dies (shared.service.die_with_parent):
                # no preexec_fn, which is unsafe in a process with threads (Zenoh's).
                env=child_env(self.env, child.env), stdout=out,
                stderr=subprocess.STDOUT if out else None, stdin=subprocess.DEVNULL,
                start_new_session=True, cwd=self.cwd,
            )
        finally:
            if out is not None:
                out.close()
        child.pids.append(child.proc.pid)
        child.started = time.monotonic()

    def poll(self, on_event=print) -> None:  # noqa: ANN001
        """Restart children that died (not when they exited 0, and not while stopping)."""
        now = time.monotonic()
        for child in self.children.values():
            if child.proc is None or child.exited is not None:
                continue
            code = child.proc.poll()
            if code is None:
                continue
            if code == 0 or self.stopping:
                child.exited = code
                continue
            if code == EXIT_BAD_INPUT:  # it would fail the same way again
                child.exited = code
                on_event(f"{child.name} refused its input: {self.last_error(child)}; not restarted")
                continue
            if code == EXIT_LOGIN_REFUSED:  # the same credentials would be refused again
                child.exited = code
                on_event(f"{child.name}'s Zenoh login was refused by the router: {self.last_error(child)}; "
                         "not restarted")
                continue
            since = self._dead_since.setdefault(child.name, now)
            if since - child.started >= self.stable_s:
                child.restarts = 0  # it ran well for a while: a crash now and then is not a loop
            # Each restart in a row waits twice as long as the one before (a crash loop backs off).
            delay = min(self.restart_delay_s * 2 ** child.restarts, MAX_RESTART_DELAY_S)
            if child.restarts >= self.max_restarts:
                child.exited = code
                on_event(f"{self._died(child, code)}; not restarted after {child.restarts} restarts in a row")
            elif now - since >= delay:
                del self._dead_since[child.name]
                child.restarts += 1
                on_event(f"{self._died(child, code)}: restarting it ({child.restarts})")
                try:
                    self._spawn(child, on_event)
                except OSError as err:  # no process to be had now (a pids limit, memory): a failed restart
                    self._dead_since[child.name] = child.started = now  # a start that ran for no time
                    on_event(f"{child.name} could not be started ({err.strerror or err}); trying again")

    def _died(self, child: Child, code: int) -> str:
        """How a child died and, from its log, why (its last line: a traceback's error); without a
        log the terminal shows it already."""
        why = "" if self.log_dir is None else f" ({self.last_error(child)})"
        return f"{child.name} {exit_text(code)}{why}"

    def log_file(self, child: Child) -> Path | None:
        """Where the child's output goes; None: this terminal."""
        return None if self.log_dir is None else self.log_dir / f"{child.name}.log"

    def last_error(self, child: Child) -> str:
        """The child's last output line, from its log file (else it is in the terminal above)."""
        log = self.log_file(child)
        if log is None:
            return "see its error above"
        try:
            line = last_line(log)  # its end only: after days the log is large
        except OSError as err:
            return f"{log}: cannot be read ({err.strerror or err})"
        # A service on a full disk dies unable to write why: say what it could not.
        return f"{log}: {line or 'no output'}{disk_full(log.parent)}"

    def refused(self) -> Child | None:
        """The first child whose Zenoh login the router refused: the run cannot heal itself."""
        return next((c for c in self.children.values() if c.exited == EXIT_LOGIN_REFUSED), None)

    def ended(self, roles: tuple[str, ...]) -> Child | None:
        """The first child of one of `roles` that ended for good (exited 0, refused, or out of restarts)."""
        return next((c for c in self.children.values() if c.role in roles and c.exited is not None), None)

    def all_ended(self, role: str) -> Child | None:
        """The last child of `role` to end for good, once every child of it has (else None). An
        actor that ended with 0 (the run's steps are done) does not count."""
        group = [c for c in self.children.values() if c.role == role]
        if not group or any(c.exited is None or c.exited == 0 for c in group):
            return None
        return group[-1]

    def running(self) -> list[Child]:
        return [c for c in self.children.values() if c.proc is not None and c.proc.poll() is None]

    def stop_all(self, timeout_s: float = 20.0, on_event=print) -> None:  # noqa: ANN001
        """SIGTERM role by role in STOP_ORDER, SIGKILL what is left after the timeout (and say so:
        a learner killed mid-checkpoint leaves the one before)."""
        self.stopping = True
        for role in STOP_ORDER:
            group = [c for c in self.children.values() if c.role == role and c.proc is not None]
            for c in group:
                if c.proc.poll() is None:
                    c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            for c in group:
                try:
                    c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    on_event(f"{c.name} did not stop within {timeout_s:g} s of SIGTERM: killed")
                    c.proc.kill()
                    c.proc.wait()
        for c in self.children.values():  # anything with a role outside STOP_ORDER
            if c.proc is not None and c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait()

    def kill_all(self, wait_s: float = 5.0) -> list[str]:
        """SIGKILL every child still running and reap it; returns their names. For a forced stop,
        from a signal handler: Popen's own wait takes a lock the interrupted stop may hold, so the
        processes are killed and reaped by pid (a killed learner leaves its last checkpoint whole:
        it lands by a rename)."""
        self.stopping = True
        alive = [c for c in list(self.children.values()) if c.proc is not None and c.proc.returncode is None]
        killed = []
        for c in alive:
            try:
                os.kill(c.proc.pid, signal.SIGKILL)  # a zombie not yet reaped takes it harmlessly
            except ProcessLookupError:
                continue
            killed.append(c)
        deadline = time.monotonic() + wait_s  # one stuck in the kernel (a device, a network disk) is left
        names = []
        for c in killed:
            while True:
                try:
                    pid, status = os.waitpid(c.proc.pid, os.WNOHANG)
                except ChildProcessError:  # reaped already, by the stop this interrupts
                    break
                if pid:
                    c.proc.returncode = os.waitstatus_to_exitcode(status)
                    if c.proc.returncode == -signal.SIGKILL:
                        names.append(c.name)
                    break
                if time.monotonic() >= deadline:
                    names.append(f"{c.name} (not yet gone)")
                    break
                time.sleep(0.01)
        return names


class StopSignals:
    """Why `nasa up` stops. The first Ctrl-C, SIGTERM or SIGHUP stops the run in order (`reason`,
    `signum`); from then on (or once the run stops by itself) a Ctrl-C or SIGTERM forces it: every
    service left is killed and `nasa up` exits at once, 128 + that signal."""

    def __init__(self, sup: Supervisor, after: str) -> None:
        self.sup = sup
        self.after = after  # said once forced: how the run goes on
        self.reason = ""
        self.signum = 0

    def install(self) -> None:
        # SIGHUP: the terminal went away (an ssh session dropped); stop in order as for SIGTERM, where
        # its default would end this process at once and leave the services to stop all together.
        for signum in STOP_SIGNALS:
            signal.signal(signum, self._on_signal)

    def _on_signal(self, signum: int, _frame: object) -> None:
        if self.signum:  # a second SIGHUP (a shell passes its own on): not a user's "force"
            return
        self.reason, self.signum = signal.Signals(signum).name, signum
        self._arm()

    def _arm(self) -> None:
        second_signal_forces("nasa up", self.after, self._force, FORCE_SIGNALS, sys.stdout.fileno())

    def _force(self) -> str:
        killed = self.sup.kill_all()
        return f"killed {', '.join(killed)}" if killed else "no service was left"

    def stopping(self) -> None:
        """The stop in order begins: say so, and that a Ctrl-C kills what is left."""
        if not self.signum:  # the run ended by itself: a first Ctrl-C now forces
            self._arm()
        again = "again " if self.signum else ""
        say(f"stopping in order ({self.reason or 'error'}); Ctrl-C {again}kills what is left")


@dataclass
class UpCommand:
    """Run the distributed system on this host: router, replay, learner, evaluator and N actors.

    Config flags are `nasa train`'s (e.g. `--task cheetah-run --image-size 48`); the same
    command again resumes the run in its folder. `--device` is the learner's device.
    """

    config: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=TrainConfig)
    preset: str = DEFAULT_PRESET
    """`paper`, `cpu-small`, or `auto`: paper on a GPU, cpu-small on a CPU."""
    actors: int = 0
    """Actor processes, each stepping its own environment; 0: chosen from the machine (nasa.layout)."""
    data: Path | None = None
    """Run folder (default runs/<task>-<algo>-up); an existing one is resumed."""
    port: int = 8000
    """Port of the learner's status API."""
    router_port: int = 7447
    """Port of the embedded Zenoh router (0: a free one)."""
    run_id: str | None = None
    """Key prefix nasa/<run_id>/ (default: from the run folder's name)."""
    evaluator: bool = True
    """Run the evaluator service (eval.csv every --eval-every env steps)."""
    learner_threads: int = 0
    """torch threads of the learner; 0: chosen from the machine (nasa.layout)."""
    learner_omp_wait: layout.OmpWait = "auto"
    """How the learner's OpenMP threads wait between parallel regions: `passive` sleep, `active`
    spin, `default` the runtime's own; `auto`: chosen from the machine (nasa.layout)."""
    evaluator_nice: int | None = None
    """CPU priority (nice) of the evaluator process; default: low on a machine of under 4 cores."""
    evaluate_in: layout.EvalWhere = "auto"
    """Where evaluations run: `process` the evaluator service (it also makes the autoencoder's view
    and videos), `learner` between the learner's updates as `nasa train` does (no pictures);
    `auto`: chosen from the machine (nasa.layout)."""
    publish_every: int = 0
    """K: the learner publishes weights every K updates, so actors act with weights up to K
    updates old (1: the latest after every update, as `nasa train` acts); 0: chosen from the
    machine (nasa.layout: 1 on a CPU, the learner's default with a GPU)."""
    actor_lead: int = 0
    """How many env steps the actors may run ahead of the learner's schedule (the replay's rate
    limiter slack, and each actor's transitions sent and not yet taken); 0: chosen from the
    machine (nasa.layout: 1 on a CPU with one actor, so it acts with the newest weights as
    `nasa train` does; else the replay's default slack, 2 x G x 16 + 8 samples)."""
    logs: bool = False
    """Write each service's output to <data>/logs/<service>.log instead of this terminal."""
    bridge: Literal["off", "stand-in", "emulator", "hardware"] = "off"
    """Gripper tasks: each actor steps its gripper through a robot bridge process, started and
    restarted here: `stand-in` (the MuJoCo stand-in in the bridge), `emulator` (the real gripper's
    driver and interlocks against an emulated servo bus, with a drawn camera), `hardware` (the real
    gripper of --bridge-config; one actor and no evaluator, as there is one gripper). The evaluator
    gets a bridge of its own. `off`: the environment in each service's process."""
    bridge_config: Path | None = None
    """The real gripper's TOML config (services/robot_bridge/example.toml), for --bridge hardware;
    the run learns at its camera.image_size."""
    zenoh_auth: str = field(default_factory=lambda: os.environ.get("NASA_ZENOH_AUTH") or RUN_AUTH)
    """Zenoh logins per role and the ACL at the router: `run` (default), the run folder's auth/,
    made for this run when it holds no users.txt; a folder (`nasa auth init`; env NASA_ZENOH_AUTH);
    `off`: no authentication, any local process may talk to the run."""


# Far above what any layout chooses, far below what brings a machine down (a process of a few
# hundred MB each).
MAX_ACTORS_PER_CORE = 8
MAX_THREADS_PER_CORE = 8


def parse_up(argv: list[str]) -> tuple[UpCommand, str]:
    """`nasa up`'s flags, through the parser every service uses; returns them and the preset used.
    A `--` (older command lines put config flags after it) is dropped."""
    if "--" in argv:
        i = argv.index("--")
        argv = [*argv[:i], *argv[i + 1 :]]
    cmd, preset = parse_with_preset(UpCommand, argv, "nasa up")
    for flag, value in (("--actors", cmd.actors), ("--learner-threads", cmd.learner_threads),
                        ("--publish-every", cmd.publish_every), ("--actor-lead", cmd.actor_lead)):
        if value < 0:
            raise ConfigError(f"{flag} must be >= 0 (0: chosen from the machine), got {value}")
    if not 1 <= cmd.port <= 65535:
        raise ConfigError(f"--port must be a TCP port, 1-65535, got {cmd.port}")
    if not 0 <= cmd.router_port <= 65535:
        raise ConfigError(f"--router-port must be a TCP port, 1-65535 (0: a free one), got {cmd.router_port}")
    cores = layout.usable_cores()
    if cmd.actors > MAX_ACTORS_PER_CORE * cores:
        raise ConfigError(
            f"--actors {cmd.actors} on {cores} core(s): at most {MAX_ACTORS_PER_CORE * cores} on this host "
            f"({MAX_ACTORS_PER_CORE} a core); each actor is a process with its own simulator, renderer and "
            "torch, and hundreds of them exhaust the machine's memory; more actors go on other hosts "
            "(docs/deployment.md)"
        )
    if cmd.learner_threads > MAX_THREADS_PER_CORE * cores:
        # Past what the cores can run, threads only wait; far past it, OpenMP cannot make them and the
        # learner aborts at its first update, again at each restart.
        raise ConfigError(f"--learner-threads {cmd.learner_threads} on {cores} core(s): at most "
                          f"{MAX_THREADS_PER_CORE * cores} on this host ({MAX_THREADS_PER_CORE} a core)")
    if cmd.run_id is not None:
        try:
            wire.check_run_id(cmd.run_id)  # a key prefix: before the run folder is made
        except ValueError as err:
            raise ConfigError(f"--run-id: {err}") from None
    check_evaluator(cmd)
    check_bridge(cmd)
    if cmd.bridge == "hardware":
        explicit = preset == "run" or "--image-size" in given_flags(argv)
        take_camera_size(cmd, explicit)
    return cmd, preset


def check_evaluator(cmd: UpCommand) -> None:
    """--no-evaluator means no evaluations (nasa.layout), so a choice of where they run, or of the
    evaluator process's priority, contradicts it; so does a priority for evaluations in the learner."""
    if not cmd.evaluator and cmd.evaluate_in != "auto":
        raise ConfigError(f"--no-evaluator with --evaluate-in {cmd.evaluate_in}: --no-evaluator turns "
                          "evaluations off; leave one of them out")
    if cmd.evaluator_nice is not None and not cmd.evaluator:
        raise ConfigError("--no-evaluator with --evaluator-nice: there is no evaluator process to renice")
    if cmd.evaluator_nice is not None and cmd.evaluate_in == "learner":
        raise ConfigError("--evaluate-in learner with --evaluator-nice: evaluations run in the learner, "
                          "there is no evaluator process to renice")


def check_bridge(cmd: UpCommand) -> None:
    """--bridge needs a task a bridge serves; the real gripper needs its config, and is one gripper."""
    if cmd.bridge != "hardware" and cmd.bridge_config is not None:
        raise ConfigError(f"--bridge-config is for --bridge hardware, not --bridge {cmd.bridge}")
    if cmd.bridge == "off":
        return
    try:
        envs.check_remote(cmd.config.env)
    except ConfigError as err:
        raise ConfigError(f"--bridge {cmd.bridge}: {err}") from None
    if cmd.evaluate_in == "learner":
        raise ConfigError(f"--bridge {cmd.bridge}: evaluations go through a bridge of their own, from the "
                          "evaluator process: --evaluate-in process (or auto)")
    if cmd.bridge == "hardware" and cmd.bridge_config is None:
        raise ConfigError("--bridge hardware needs --bridge-config FILE (the gripper's TOML config)")
    if cmd.bridge == "hardware" and cmd.actors not in (0, 1):
        raise ConfigError(f"--bridge hardware drives one gripper: --actors 1, not {cmd.actors}")
    if cmd.bridge == "hardware" and (cmd.evaluate_in == "process" or cmd.evaluator_nice is not None):
        flag = "--evaluate-in process" if cmd.evaluate_in == "process" else "--evaluator-nice"
        raise ConfigError(f"--bridge hardware with {flag}: the one gripper is the actor's, so the run has no "
                          f"evaluator; leave {flag} out")


def take_camera_size(cmd: UpCommand, explicit: bool) -> None:
    """--bridge hardware: the real camera's frames have its config's `camera.image_size`, so the run
    learns at that size. A size the user chose (or the run's config holds) that differs is refused
    here, before anything starts, rather than by the actor at its first frame."""
    from services.robot_bridge.config import GripperConfigError, load

    try:
        camera = load(cmd.bridge_config).camera
    except GripperConfigError as err:
        raise ConfigError(f"--bridge-config: {err}") from None
    env = cmd.config.env
    if explicit and env.image_size != camera.image_size:
        raise ConfigError(f"--bridge hardware: the run's image size is {env.image_size} but the camera of "
                          f"{cmd.bridge_config} gives {camera.image_size}x{camera.image_size} frames "
                          f"(camera.image_size); make them the same, or leave --image-size out to "
                          f"take the camera's")
    env.image_size = camera.image_size
    validate(cmd.config)


def bridge_id(run_id: str, i: int | str) -> str:
    """Actor i's robot bridge: bridges' keys are not under a run, so the id names the run."""
    return f"{run_id}-{i}"


def with_bridges(cmd: UpCommand, argv: dict[str, list[str]], run_id: str) -> dict[str, list[str]]:
    """`service_argv`'s children plus, for --bridge, one robot bridge per actor (`robot_bridge-<i>`)
    and one for the evaluator (`robot_bridge-eval`), started first, each client pointed at its
    own; unchanged when --bridge is off."""
    if cmd.bridge == "off":
        return argv
    c = cmd.config
    how = {"emulator": ["--emulate"], "hardware": ["--config", str(cmd.bridge_config)]}.get(cmd.bridge, [])
    actors = [name for name in argv if name.startswith("actor-")]

    def bridge(ident: int | str, seed: int) -> list[str]:
        return ["--bridge-id", bridge_id(run_id, ident), "--task", c.env.task, "--seed", str(seed),
                "--image-size", str(c.env.image_size), "--camera-id", str(c.env.camera_id),
                "--render-quality", c.env.render_quality, *how]

    bridges = {f"robot_bridge-{i}": bridge(i, c.seed + i) for i in range(len(actors))}
    if "evaluator" in argv:  # its own bridge, seeded as an in-process evaluator's environment
        bridges["robot_bridge-eval"] = bridge("eval", c.seed + EVAL_SEED_OFFSET)
    out = {**bridges, **argv}
    for i, name in enumerate(actors):
        out[name] = [*argv[name], "--bridge", bridge_id(run_id, i)]
    if "evaluator" in argv:
        out["evaluator"] = [*argv["evaluator"], "--bridge", bridge_id(run_id, "eval")]
    return out


def run_folder(cmd: UpCommand) -> Path:
    c = cmd.config
    return cmd.data or Path("runs") / f"{c.env.task}-{c.algo}-up"


def prepare(cmd: UpCommand, data: Path) -> RunConfig:
    """Check the task and the run folder before any service starts: a new folder gets the resolved
    config.json, a resumed one must hold the same settings (ConfigMismatch), the step budget aside."""
    envs.check_task(cmd.config.env.task)  # here once, rather than from every service
    return run_config.open_folder(cmd.config, data, may_change=run_config.RESUME_MAY_CHANGE)


def layout_of(cmd: UpCommand, gpu: bool, cores: int | None = None) -> layout.Layout:
    """The services' layout: the flags where given, the rest chosen from the machine."""
    # One real gripper, whatever the machine: the actor's; no second one to evaluate on.
    hardware = cmd.bridge == "hardware"
    return layout.choose(cores or layout.usable_cores(), gpu, 1 if hardware else cmd.actors,
                         cmd.learner_threads, cmd.evaluator and not hardware, cmd.evaluator_nice,
                         cmd.learner_omp_wait, cmd.evaluate_in,  # `learner` with a bridge: refused
                         cmd.publish_every, cmd.actor_lead)


def service_argv(cmd: UpCommand, data: Path, lay: layout.Layout) -> dict[str, list[str]]:
    """Each service's flags: the run's config.json (written by `prepare`) and its own role's flags."""
    common = ["--run-config", str(data / run_config.CONFIG_FILE)]
    lead = lay.lead_argv(cmd.config.updates_per_step)
    out = {
        # `up` has checked the camera (envs.check_camera): the replay need not load the model again.
        "replay": [*common, "--data", str(data), "--camera-checked", *lead["replay"]],
        "learner": [*common, "--data", str(data), "--port", str(cmd.port),
                    "--threads", str(lay.learner_threads)],
    }
    if lay.publish_every:
        out["learner"] += ["--publish-every", str(lay.publish_every)]
    if lay.eval_in_learner:
        out["learner"].append("--eval-between-updates")
    elif lay.evaluator:
        out["evaluator"] = [*common, "--data", str(data)]  # the autoencoder's view and videos go there
    for i in range(lay.actors):
        out[f"actor-{i}"] = [*common, "--actor-id", str(i), *lead["actor"]]
    return out


def up(argv: list[str]) -> None:
    die_with_parent()  # under a launcher: its death stops the run, not leaves it holding ports and cores
    from shared.device import resolve_device

    cmd, preset = parse_up(argv)
    c = cmd.config
    data = run_folder(cmd)
    device = resolve_device(c.device)
    from shared.faults import check_port_free, lock_run

    envs.check_task(c.env.task)  # an unknown task leaves no folder behind
    envs.check_camera(c.env)
    if cmd.router_port and cmd.router_port == cmd.port:
        raise ConfigError(f"--port and --router-port are both {cmd.port}: the status API and the router "
                          "each need a port of their own")
    what = f"nasa up (status port {cmd.port})"
    # A folder in use: its lock first, which waits for the services of an earlier launch still
    # stopping (its learner holds the status port until it exits); a new folder only after the
    # ports, so a refusal leaves none.
    lock = lock_run(data, what, say=say) if data.exists() else None
    check_port_free("127.0.0.1", cmd.port, "the status", "--port")
    if cmd.router_port:
        check_port_free("127.0.0.1", cmd.router_port, "the router", "--router-port")
    lock = lock or lock_run(data, what, say=say)  # held until this process ends
    prepare(cmd, data)
    how = f"auto: {'GPU' if device.type == 'cuda' else 'no GPU'}, device {device}" if cmd.preset == "auto" \
        else f"device {device}"
    lay = layout_of(cmd, device.type == "cuda")
    say(f"preset {preset} ({how}); {c.algo} on {c.env.task}, {lay.actors} actor(s)")
    say(lay.describe())
    run_id = cmd.run_id or re.sub(r"[^A-Za-z0-9_.\-]", "-", data.resolve().name)
    router_port = cmd.router_port or free_port()
    endpoint = f"tcp/127.0.0.1:{router_port}"
    env = {**os.environ, "NASA_ZENOH_CONNECT": endpoint, "NASA_RUN_ID": run_id}
    auth = up_auth(cmd, data, run_id, env)
    from shared.zenoh_session import open_router

    sup = Supervisor(env, data / "logs" if cmd.logs else None)
    stop = StopSignals(sup, f"the same command resumes the run from {data}")
    stop.install()
    ended: Child | None = None
    with open_router(endpoint, auth=auth):
        try:
            start_all(sup, stop, cmd, lay, with_bridges(cmd, service_argv(cmd, data, lay), run_id))
            if not stop.reason:
                say(f"run {run_id} in {data}; router {endpoint}; status http://127.0.0.1:{cmd.port}/status")
            while not stop.reason:
                sup.poll(say)
                if end := run_ends(sup, auth):
                    ended, stop.reason = end
                    break
                time.sleep(0.2)
        finally:
            stop.stopping()
            sup.stop_all(on_event=say)
    say("stopped")
    lock.close()
    if ended is not None and ended.exited:
        # Refused input or a refused login: the same command fails again until it is fixed.
        sys.exit(EXIT_BAD_INPUT if ended.exited in (EXIT_BAD_INPUT, EXIT_LOGIN_REFUSED) else 1)
    if stop.signum:  # 130, 143, 129 (as `nasa train`): a run stopped from outside is not a finished one
        sys.exit(128 + stop.signum)


TEST_START_PAUSE = "NASA_TEST_UP_START_PAUSE_S"
"""Tests only: seconds `nasa up` holds its start-up after each service it starts (a stop signal ends
the hold), so a test can signal it while services are still being started."""


def start_all(sup: Supervisor, stop: StopSignals, cmd: UpCommand, lay: layout.Layout,
              argv: dict[str, list[str]]) -> None:
    """Start each service of `argv` in turn; a stop signal meanwhile starts no more of them (the
    caller stops those already started, in order)."""
    pause = float(os.environ.get(TEST_START_PAUSE) or 0)
    for i, (name, args) in enumerate(argv.items()):
        if stop.reason:
            say(f"{stop.reason} while starting the services: {', '.join(list(argv)[i:])} not started")
            return
        role = name.split("-")[0]
        sup.add(name, role, args, nice=lay.evaluator_nice if role == "evaluator" else 0,
                env=omp_env(cmd, lay, role))
        held_until = time.monotonic() + pause
        while not stop.reason and time.monotonic() < held_until:
            time.sleep(0.05)


def run_ends(sup: Supervisor, auth: Path | None) -> tuple[Child, str] | None:
    """The child whose end ends the run, and why; None while it goes on. The run cannot go on
    without its learner or its replay, nor without any actor, nor with a service whose login the
    router refuses (the run's credentials do not change while it runs)."""
    if (refused := sup.refused()) is not None:
        where = f" ({auth})" if auth is not None else ""
        return refused, (f"{refused.name}'s Zenoh login was refused by the run's router: its credentials"
                         f"{where} are not the router's, and a restart would not change them")
    ended = sup.ended(("learner", "replay")) or sup.all_ended("actor")
    if ended is None:
        return None
    if ended.role == "actor":  # all_ended: none of them with 0
        return ended, f"no actor is left: the last, {ended.name}, {exit_text(ended.exited)}"
    if ended.exited == 0:
        return ended, f"the run is done ({ended.name} finished)"
    return ended, f"{ended.name} {exit_text(ended.exited)}"


def say(msg: str) -> None:
    """One line of `nasa up`'s on stdout; none where stdout is gone (a closed terminal, a closed
    pipe): the run and its stop go on without it."""
    try:
        print(f"nasa up: {msg}", flush=True)
    except OSError:
        # Nowhere from now on: the line left in the buffer would fail again at exit (exit 120).
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115


def omp_env(cmd: UpCommand, lay: layout.Layout, role: str) -> dict[str, str | None]:
    """A service's OpenMP wait policy from the layout; an OMP_WAIT_POLICY the user set wins, except
    over the learner's own --learner-omp-wait."""
    if "OMP_WAIT_POLICY" in os.environ and not (role == "learner" and cmd.learner_omp_wait != "auto"):
        return {}
    return lay.omp_env(role)


def up_auth(cmd: UpCommand, data: Path, run_id: str, env: dict[str, str]) -> Path | None:
    """The run's auth folder (made for this run when it has no credentials yet), passed on to every
    service in `env`; None with --zenoh-auth off."""
    if cmd.zenoh_auth == "off":
        env.pop("NASA_ZENOH_AUTH", None)
        return None
    from shared import zenoh_auth

    folder = data / "auth" if cmd.zenoh_auth == RUN_AUTH else Path(cmd.zenoh_auth)
    if not (folder / USERS_FILE).exists():
        try:
            zenoh_auth.init(folder, run_id)
        except OSError as err:  # not a folder, not writable, a full disk: before any service starts
            raise ConfigError(f"--zenoh-auth {folder}: cannot write the run's credentials: {err}") from None
    if cmd.zenoh_auth == RUN_AUTH:
        # The run's own folder: its ACL follows the code that runs it (a resume after an
        # upgrade); its passwords stay.
        try:
            zenoh_auth.write_acl(folder, run_id)
        except OSError as err:  # a read-only or full disk on a resume
            raise ConfigError(f"--zenoh-auth {folder}: cannot write the run's access rules: {err}") from None
    zenoh_auth.check_acl(folder, run_id)
    env["NASA_ZENOH_AUTH"] = str(folder.resolve())
    say(f"Zenoh logins and access control from {folder} (--zenoh-auth off: none)")
    return folder


@dataclass
class StatusCommand:
    """Print the status of a running system (the learner's GET /status); with --data, a
    stopped run's last status (<data>/learner/status.json) when that run's learner is not
    the one answering."""

    url: str = "http://127.0.0.1:8000/status"
    """The learner's status API: its /status, or just its address (http://HOST:PORT)."""
    data: Path | None = None
    """A run folder: its last status when its learner is not the one answering at --url."""
    serve: bool = False
    """With --data: serve the stopped run's dashboard (http://HOST:PORT/) until interrupted."""
    host: str = "127.0.0.1"
    """With --serve: the address to serve the dashboard on."""
    port: int = 8000
    """With --serve: the port to serve the dashboard on."""


def status(argv: list[str]) -> None:
    """`nasa status [--url URL] [--data DIR] [--serve]`: print the learner's /status, or the last one
    it left in DIR when it is not running; with --data DIR --serve, serve a stopped run's dashboard."""
    import json

    cmd = read_flags(StatusCommand, argv, "nasa status")
    if cmd.serve:
        if cmd.data is None:
            print("nasa status: --serve needs --data DIR (a stopped run's folder)", file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)
        serve_stopped(cmd.data, cmd.host, cmd.port)
        return
    url = status_url(cmd.url)
    live, why = read_live_status(url)
    not_running = f"the learner is not running at {url}"
    if live is not None and cmd.data is not None and (other := other_run(live, cmd.data)):
        live, why = None, other
        not_running = f"the learner at {url} is not this run's: {other}"
    if live is not None:
        print(json.dumps(live, indent=2))
        return
    if cmd.data is None:
        print(f"nasa status: cannot read {url}: {why} (a stopped run: --data DIR)", file=sys.stderr)
        sys.exit(1)
    from services.learner.status_api import StoppedRunError, read_final_status

    try:
        final = read_final_status(cmd.data)
    except StoppedRunError as stopped:
        print(f"nasa status: cannot read {url}: {why}; and {stopped}", file=sys.stderr)
        sys.exit(1)
    saved = cmd.data / "learner" / "status.json"
    print(f"nasa status: {not_running}; this run's last status, from {saved}:", file=sys.stderr)
    print(json.dumps(final, indent=2))


def status_url(url: str) -> str:
    """The learner's /status at `url`; a bare address (http://host:port) means its /status. A
    `url` that is no http(s) address is a ConfigError."""
    from urllib.parse import urlsplit, urlunsplit

    import httpx

    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 -- urlsplit checks the port only when asked for it
        httpx.URL(url)  # and httpx refuses some that urlsplit lets through
    except (ValueError, httpx.InvalidURL) as err:
        raise ConfigError(f"--url {url!r} is not an address: {err}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigError(f"--url {url!r} is not an address of the learner's status API: give "
                          "http://HOST:PORT or http://HOST:PORT/status")
    return urlunsplit(parts._replace(path="/status")) if parts.path in ("", "/") else url


def read_live_status(url: str) -> tuple[dict | None, str]:
    """(the status `url` answers, "") or (None, why not)."""
    import httpx

    try:
        response = httpx.get(url, timeout=5.0)
        response.raise_for_status()
        body = response.json()
    except httpx.HTTPError as err:
        return None, str(err)
    except ValueError:
        return None, "it answers, but not with JSON: is it the learner's status API (/status)?"
    if not isinstance(body, dict):
        return None, "it answers JSON that is not a status: is it the learner's status API (/status)?"
    return body, ""


def other_run(live: dict, data: Path) -> str | None:
    """Why the status `live` is not that of the run in folder `data` (another run's learner
    answers there), or None when it may be."""
    from services.learner.status_api import StoppedRunError, read_final_status

    try:
        saved_id = read_final_status(data).get("run_id")
    except StoppedRunError:  # none saved, or unreadable: the settings may still tell
        saved_id = None
    if saved_id is not None and live.get("run_id") != saved_id:
        return f"it serves run {live.get('run_id')!r}, and {data} holds run {saved_id!r}"
    try:
        folder = run_config.read_folder(data)
        digest = run_config.RunConfig.from_dict(folder).digest() if folder is not None else None
    except (ConfigError, TypeError, ValueError, KeyError):
        return None
    if digest is not None and live.get("config_digest") != digest:
        return f"it serves run {live.get('run_id')!r}, whose settings are not those of the run in {data}"
    return None


def serve_stopped(data: Path, host: str, port: int) -> None:
    """A stopped run's dashboard, status, history and media from its folder, until Ctrl-C."""
    import uvicorn

    from services.learner.status_api import GuardedH11Protocol, StoppedRunError, folder_app
    from shared.faults import check_port_free

    try:
        app = folder_app(data)
    except StoppedRunError as err:
        print(f"nasa status: {err}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    check_port_free(host, port, "the dashboard's", "--port")
    print(f"nasa status: the dashboard of {data} on http://{host}:{port}/ (Ctrl-C ends it)", flush=True)
    # The learner's limits on connections and slow request heads, so idle clients cannot take it.
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False,
                            http=GuardedH11Protocol)
    # Server.run, not uvicorn.run, which swallows the Ctrl-C the server raises again once it has
    # shut down: `nasa` then says it was interrupted and exits 130, as it exits 143 on SIGTERM.
    uvicorn.Server(config).run()
