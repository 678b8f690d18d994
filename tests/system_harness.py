"""Runs the distributed system as real processes on loopback for the system tests and bench.

The router runs in the test process (as `nasa up` runs it); every service is
its own process started by nasa.up's Supervisor, with free ports and tiny
settings (32 px, narrow nets, fast render, G = 1, warm-up 20).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import httpx

from nasa.up import Supervisor, free_port, layout_of, parse_up, prepare, service_argv, with_bridges
from shared.zenoh_session import open_router

REPO = Path(__file__).resolve().parents[1]
WARMUP = 20
ERROR_BUFFER = 16
TINY = [
    "--image-size", "32", "--warmup-steps", str(WARMUP), "--batch-size", "32", "--updates-per-step", "1",
    "--hidden-dim", "64", "--latent-dim", "32", "--ensemble-hidden-dim", "32", "--num-filters", "16",
    "--render-quality", "fast", "--replay-capacity", "10000",
]


def assert_eval_steps(steps: list[int], total: int, every: int) -> None:
    """A distributed run's evaluations: step 0 and the last eval step always, in order, each at a
    multiple of `every`. The evaluator skips the steps between when it is slower than training
    (by design: it plays the newest eval step's weights), which a loaded machine can make it."""
    last = total // every * every
    assert steps[0] == 0 and steps[-1] == last, steps
    assert steps == sorted(set(steps)) and all(s % every == 0 for s in steps), steps


def tail_logs(folder: Path, lines: int = 15) -> str:
    """The last lines of every service log in `folder`, for an assertion's message."""
    out = []
    for f in sorted(folder.glob("*.log")):
        out.append(f"== {f.name}\n" + "\n".join(f.read_text(errors="replace").splitlines()[-lines:]))
    return "\n".join(out)


class System:
    def __init__(self, data: Path, actors: int = 2, steps: int = 300, extra: list[str] | None = None,
                 restart_delay_s: float = 1.0, evaluator: bool = True,
                 replay_extra: list[str] | None = None, learner_extra: list[str] | None = None) -> None:
        self.data = data
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = open_router(self.endpoint)
        env = {**os.environ, "NASA_ZENOH_CONNECT": self.endpoint, "NASA_RUN_ID": f"t{self.port}",
               "PYTHONPATH": str(REPO)}
        self.sup = Supervisor(env, data / "logs", restart_delay_s=restart_delay_s, cwd=str(REPO))
        # As `nasa up` does: one parse, the run's config.json written once, each service pointed at it.
        cmd, _ = parse_up([
            "--preset", "cpu-small", "--task", "cartpole-balance", "--algo", "nasa_td3",
            "--steps", str(steps),
            "--device", "cpu", "--actors", str(actors), "--port", str(self.port), "--learner-threads", "1",
            *TINY, *(extra or []),
        ])
        cmd.evaluator = evaluator
        prepare(cmd, data)
        # robot bridges, for --bridge
        argv = with_bridges(cmd, service_argv(cmd, data, layout_of(cmd, gpu=False)), f"t{self.port}")
        argv["replay"] += ["--error-buffer", str(ERROR_BUFFER), *(replay_extra or [])]
        argv["learner"] += learner_extra or []
        for name, args in argv.items():
            self.sup.add(name, name.split("-")[0], args)
        self.url = f"http://127.0.0.1:{self.port}"

    def status(self) -> dict | None:
        try:
            r = httpx.get(self.url + "/status", timeout=2.0)
            return r.json() if r.status_code == 200 else None
        except httpx.HTTPError:
            return None

    def wait_for(self, what: str, pred: Callable[[dict], bool], timeout: float = 120.0,
                 poll_supervisor: bool = True, or_run_done: bool = False) -> dict | None:
        """The first status that satisfies pred; with `or_run_done`, None once the learner
        has finished the run and exited (a fast run can end between two polls)."""
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            if poll_supervisor:
                self.sup.poll(lambda msg: None)
            s = self.status()
            if s is not None:
                last = s
                if pred(s):
                    return s
            elif or_run_done and self.sup.children["learner"].exited == 0:
                return None
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what}; last status: {last}\n{self.logs()}")

    def wait_exit(self, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sup.poll(lambda msg: None)
            if not self.sup.running():
                return
            time.sleep(0.2)
        names = [c.name for c in self.sup.running()]
        raise AssertionError(f"still running after {timeout} s: {names}\n{self.logs()}")

    def logs(self) -> str:
        return tail_logs(self.data / "logs")

    def close(self) -> None:
        try:
            self.sup.stop_all(timeout_s=15.0)
        finally:
            self.router.close()

    def leftover_pids(self) -> list[int]:
        """Pids of every process ever started that still exists (zombies count as gone)."""
        left = []
        for child in self.sup.children.values():
            for pid in child.pids:
                try:
                    state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
                except (FileNotFoundError, ProcessLookupError):
                    continue
                if state != "Z":
                    left.append(pid)
        return left
