"""The GPU check: what needs a CUDA device, in one bounded run that ends with one JSON line.

    scripts/gpu-check.sh            (sets up, then runs this; on a machine without a GPU it
                                     says so in one line and runs nothing)
    python -m bench.gpu [--budget-s 510] [--up-seconds 180]
    python -m bench.gpu missing     (the project's requirements this Python cannot import;
                                     standard library only, for the setup step)

Steps, each in a child process with a timeout cut to the time left:
1. `pytest -m cuda tests/test_cuda.py`: CPU/GPU agreement, checkpoints across devices;
2. `bench.learner --device cuda` at the paper's settings (batch 128, the reference's
   widths): updates/s, scoring, FLOP/s against the GPU's measured fp32/TF32/BF16 peaks;
3. `bench.update_profile --device cuda`: updates/s under other CUDA settings and batches, and
   the host's, the device's and the wall time per update (what bounds an update);
4. `nasa up --preset paper --device cuda --actors 8 --task cheetah-run` for
   `--up-seconds`, its /status polled (updates/s, env steps/s, updates per env step)
   and the GPU's memory and load read from nvidia-smi; then stopped.
The last line printed is one JSON object; a step that failed or ran out of time
says so in it, and `ok` is false.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.request
from pathlib import Path

from bench import processes

ROOT = Path(__file__).resolve().parents[1]
UP_ARGS = ["--preset", "paper", "--device", "cuda", "--actors", "8", "--task", "cheetah-run"]
UP_PROFILE_S = 45.0  # the up step's measured window, once the learner updates
STATUS_KEYS = ("updates_per_s", "env_steps_per_s", "updates_per_env_step")
LEARNER_KEYS = (
    "updates_per_s", "score_ms_per_transition", "sgemm_peak_gflops", "matmul_peak_gflops", "update_gflop",
    "update_fraction_of_peak", "update_fraction_of_tf32_peak", "update_fraction_of_bf16_peak",
    "part_fraction_of_peak", "score_fraction_of_peak", "variant_updates_per_s",
    "variant_score_ms_stored_order", "machine",
)  # fmt: skip
PROFILE_KEYS = (
    "updates_per_s", "profiled_wall_s_per_update", "host_s_per_update", "device_busy_s_per_update",
    "kernel_launches_per_update",
)  # fmt: skip


# -- setup --------------------------------------------------------------------------


def requirement_name(requirement: str) -> str:
    return re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0].strip()


# Requirements that no step of the check imports: the real gripper's camera and servos, video
# files, TLS certificates, and the dev tools for linting, the browser and deployment files. An
# offline GPU machine can then be set up from a small carried folder (docs/benchmarks-reference.md).
NOT_USED_BY_THE_CHECK = frozenset({
    "opencv-contrib-python-headless", "dynamixel-sdk", "pyserial", "imageio-ffmpeg", "cryptography",
    "ruff", "playwright", "kubernetes-validate", "compose-spec",
    "py-spy",  # used where present (the learner's lock profile), never needed
})  # fmt: skip


def missing_requirements(
    pyproject: Path = ROOT / "pyproject.toml", extras: tuple[str, ...] = ("dev",),
    unused: frozenset[str] = NOT_USED_BY_THE_CHECK,
) -> list[str]:
    """The project's requirements (runtime and `extras`, less `unused`) not installed here; any
    installed version counts, since a GPU machine brings its own CUDA build of torch."""
    project = tomllib.loads(pyproject.read_text())["project"]
    wanted = list(project["dependencies"])
    for extra in extras:
        wanted += project.get("optional-dependencies", {}).get(extra, [])
    missing = []
    for req in wanted:
        if requirement_name(req).lower() in unused:
            continue
        try:
            importlib.metadata.version(requirement_name(req))
        except importlib.metadata.PackageNotFoundError:
            missing.append(req)
    return missing


# -- steps ----------------------------------------------------------------------------


class Budget:
    """The time left of the whole check; each step gets at most what remains less a reserve."""

    def __init__(self, seconds: float, clock=time.monotonic) -> None:
        self.clock = clock
        self.deadline = clock() + seconds

    def left(self) -> float:
        return self.deadline - self.clock()

    def step_timeout(self, wanted: float, reserve: float) -> float:
        """min(wanted, time left - reserve); 0 when nothing is left for this step."""
        return max(0.0, min(wanted, self.left() - reserve))


def run_child(cmd: list[str], timeout: float, env: dict | None = None) -> dict:
    """Run a command in its own process group; on timeout the whole group is killed."""
    if timeout <= 0:
        return {"rc": None, "error": "skipped: out of time", "seconds": 0.0, "output": ""}
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)  # fmt: skip
    try:
        output, _ = proc.communicate(timeout=timeout)
        result = {"rc": proc.returncode}
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        result = {"rc": None, "error": f"timed out after {timeout:.0f} s"}
    except BaseException:  # Ctrl-C, SIGTERM: in its own session, no signal reaches the child but this
        stop_group(proc, grace_s=0.0)
        raise
    result["seconds"] = round(time.perf_counter() - start, 1)
    result["output"] = output or ""
    return result


def pytest_counts(output: str) -> dict[str, int]:
    """passed / failed / skipped / error counts from pytest's summary line."""
    counts = {}
    for number, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", output):
        counts["error" if word.startswith("error") else word] = int(number)
    return counts


def last_json(output: str) -> dict | None:
    for line in reversed(output.strip().splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                return None
    return None


STEPS = ("tests", "learner", "profile", "up")
# The seconds each step needs to be left when an earlier step starts, so that an earlier step that
# hangs cannot take them; a skipped step needs none. With the default budget every step fits.
NEEDS_S = {"tests": 0.0, "learner": 60.0, "profile": 50.0, "up": 220.0}


def reserve_after(name: str, skip: set[str]) -> float:
    """The seconds that the steps after `name`, less those skipped, need to be left."""
    later = STEPS[STEPS.index(name) + 1 :]
    return sum(NEEDS_S[step] for step in later if step not in skip)


def step_tests(budget: Budget, reserve: float) -> dict:
    cmd = [sys.executable, "-m", "pytest", "-q", "-m", "cuda", "-p", "no:cacheprovider", "tests/test_cuda.py"]
    result = run_child(cmd, budget.step_timeout(150, reserve))
    out = {"rc": result["rc"], "seconds": result["seconds"], **pytest_counts(result["output"])}
    if result["rc"] != 0:
        out["error"] = result.get("error") or "tests failed"
        out["tail"] = result["output"][-1500:]
    return out


def json_step(cmd: list[str], timeout: float, keys: tuple[str, ...]) -> dict:
    """A benchmark run as a child: `keys` of its last JSON line, or an error with its output's tail."""
    result = run_child(cmd, timeout)
    summary = last_json(result["output"]) if result["rc"] == 0 else None
    if summary is None:
        return {"rc": result["rc"], "seconds": result["seconds"], "error": result.get("error") or "no result",
                "tail": result["output"][-1500:]}  # fmt: skip
    return {"seconds": result["seconds"], **{k: summary[k] for k in keys if k in summary}}


def step_learner(budget: Budget, rounds: int, updates: int, reserve: float) -> dict:
    cmd = [sys.executable, "-m", "bench.learner", "--device", "cuda", "--rounds", str(rounds),
           "--updates", str(updates), "--score-repeats", "5", "--peak-seconds", "0.5",
           "--variants", "nasa_td3+bf16"]  # fmt: skip
    return json_step(cmd, budget.step_timeout(150, reserve), LEARNER_KEYS)


def step_profile(budget: Budget, updates: int, reserve: float) -> dict:
    """bench.update_profile on CUDA: settings compared; host, device and wall time per update."""
    cmd = [sys.executable, "-m", "bench.update_profile", "--device", "cuda", "--updates", str(updates)]
    return json_step(cmd, budget.step_timeout(120, reserve), PROFILE_KEYS)


# -- nasa up ------------------------------------------------------------------------------


def gpu_sample() -> dict | None:
    """Used memory (MiB) and load (%) of GPU 0 from nvidia-smi; None without it."""
    if shutil.which("nvidia-smi") is None:
        return None
    try:
        query = ["--query-gpu=memory.used,utilization.gpu", "--format=csv,noheader,nounits", "-i", "0"]
        line = subprocess.run(
            ["nvidia-smi", *query], capture_output=True, text=True, timeout=10
        ).stdout.strip()
        used, load = (float(x) for x in line.split(","))
    except (subprocess.SubprocessError, ValueError, OSError):
        return None
    return {"memory_used_mib": used, "utilization_pct": load}


def get_status(port: int) -> dict | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=5) as response:
            return json.load(response)
    except (OSError, ValueError):
        return None


def summarize_up(samples: list[dict], gpu: list[dict]) -> dict:
    """The run's figures from /status samples (in time order) and nvidia-smi samples: the last
    status's rates and counts, the best rates seen once updates began, peak GPU memory."""
    out: dict = {"status_samples": len(samples)}
    if samples:
        last = samples[-1]
        out |= {k: last.get(k) for k in ("env_steps", "updates", *STATUS_KEYS)}
        learning = [s for s in samples if s.get("updates", 0) > 0]
        for key in ("updates_per_s", "env_steps_per_s"):
            values = [s[key] for s in learning if s.get(key) is not None]
            out[f"max_{key}"] = max(values) if values else None
            out[f"median_{key}"] = statistics.median(values) if values else None
        out["replay_size"] = last.get("replay", {}).get("size")
    if gpu:
        out["gpu_memory_max_mib"] = max(g["memory_used_mib"] for g in gpu)
        out["gpu_utilization_mean_pct"] = round(statistics.fmean(g["utilization_pct"] for g in gpu), 1)
    return out


def stop_group(proc: subprocess.Popen, grace_s: float = 30.0) -> int | None:
    """SIGINT to nasa up (it stops its services), then SIGKILL to the group if it lingers."""
    return processes.stop_group(proc, ((signal.SIGINT, grace_s),))


def step_up(budget: Budget, seconds: float, port: int, poll_s: float = 5.0) -> dict:
    run_for = min(seconds, budget.left() - 60)
    if run_for < 30:
        return {"error": "skipped: out of time"}
    from shared.service import followed  # not at the top: shared needs what the set-up step installs

    data = Path(tempfile.mkdtemp(prefix="gpu-check-up-"))
    cmd = [sys.executable, "-m", "nasa.cli", "up", *UP_ARGS, "--data", str(data / "run"),
           "--port", str(port), "--router-port", "0", "--logs"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            errors="replace", start_new_session=True, env=followed())  # fmt: skip
    output = processes.Drain(proc.stdout)  # read all along, or nasa up stalls once the pipe is full
    samples, gpu, start = [], [], time.monotonic()
    window = UpWindow(proc.pid, port, data)
    try:
        while time.monotonic() - start < run_for and proc.poll() is None:
            time.sleep(poll_s)
            status = get_status(port)
            if status is not None:
                samples.append(status)
                if status.get("updates", 0) > 0:
                    window.tick(left_s=run_for - (time.monotonic() - start))
            if (g := gpu_sample()) is not None:
                gpu.append(g)
        exited_early = proc.poll() is not None
        profile = window.result()
    except BaseException:  # nasa up runs in a session of its own: only this stops it
        stop_group(proc)
        shutil.rmtree(data, ignore_errors=True)
        raise
    rc = stop_group(proc)
    out = {"seconds": round(time.monotonic() - start, 1), "args": UP_ARGS, **summarize_up(samples, gpu),
           "profile": profile}
    if exited_early or not samples:
        out["error"] = f"nasa up exited early (rc {rc})" if exited_early else "no /status answered"
        out["tail"] = "".join(output.lines())[-1500:] + logs_tail(data / "run" / "logs")
    shutil.rmtree(data, ignore_errors=True)
    return out


class UpWindow:
    """bench.up_profile's measurement over one window of the run, once the learner updates: each
    service's CPU, the learner's wall clock split (scoring apart), and, where py-spy is present,
    who holds the learner's interpreter lock (bench.gil_profile)."""

    def __init__(self, launcher: int, port: int, folder: Path, seconds: float = UP_PROFILE_S) -> None:
        self.launcher, self.folder, self.seconds = launcher, folder, seconds
        self.url = f"http://127.0.0.1:{port}"
        self.pids: dict[str, int] = {}
        self.gil: object = None
        self.first: dict | None = None
        self.last: dict | None = None
        self.error = ""

    def tick(self, left_s: float) -> None:
        """Called while the learner updates: opens the window (if the run has time for it), closes it."""
        from bench import up_profile

        try:
            if self.first is None and left_s > self.seconds + 10:
                self.pids = {"launcher+router": self.launcher, **up_profile.service_pids(self.launcher)}
                self.first = up_profile.snapshot(self.url, self.pids)
                learner = self.pids.get("learner")
                self.gil = up_profile.gil_recording(learner, self.seconds, self.folder)
            elif self.first is not None and self.last is None and \
                    time.monotonic() - self.first["t"] >= self.seconds:
                self.last = up_profile.snapshot(self.url, self.pids)
        except Exception as err:  # noqa: BLE001 -- the profile is extra: it never fails the step
            self.error = f"{type(err).__name__}: {err}"

    def result(self) -> dict:
        from bench import up_profile

        if self.first is None or self.last is None:
            if isinstance(self.gil, up_profile.Recording):
                self.gil.proc.kill()
            return {"error": self.error or "skipped: the learner updated too briefly for the window"}
        free = {"per_sampled_batch_s": 0.0, "per_frame_s": 0.0, "batch_bytes": 0}
        out = up_profile.measure(self.first, self.last, free, up_profile.usable_cores())
        out.pop("wire")
        return out | {"learner_gil": up_profile.gil_result(self.gil)}


def logs_tail(folder: Path, chars: int = 600) -> str:
    if not folder.is_dir():
        return ""
    return "".join(
        f"\n[{p.name}] {p.read_text(errors='replace')[-chars:]}" for p in sorted(folder.glob("*.log"))
    )


# -- the check ------------------------------------------------------------------------------


def assemble(gpu_name: str | None, steps: dict[str, dict], seconds: float) -> dict:
    """The one JSON line: each step's figures, and `ok` when every step ran without error."""
    ok = all("error" not in step for step in steps.values())
    return {"check": "gpu", "ok": ok, "gpu": gpu_name, "seconds": round(seconds, 1), **steps}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command", nargs="?", choices=("check", "missing"), default="check")
    p.add_argument("--budget-s", type=float, default=510.0, help="the whole check, setup excluded")
    p.add_argument("--up-seconds", type=float, default=180.0)
    p.add_argument("--port", type=int, default=8765, help="the learner's status port during nasa up")
    p.add_argument("--rounds", type=int, default=2, help="bench.learner rounds")
    p.add_argument("--updates", type=int, default=20, help="bench.learner timed updates per round")
    p.add_argument("--profile-updates", type=int, default=50, help="bench.update_profile timed updates")
    p.add_argument("--skip", default="", help="comma-separated steps to skip: tests,learner,profile,up")
    args = p.parse_args(argv)
    if unknown := set(filter(None, args.skip.split(","))) - set(STEPS):
        p.error(f"--skip: unknown step(s) {', '.join(sorted(unknown))}; the steps are {', '.join(STEPS)}")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.command == "missing":
        print(" ".join(missing_requirements()))
        return
    import torch

    if not torch.cuda.is_available():
        print(json.dumps(assemble(None, {"cuda": {"error": "torch sees no CUDA device"}}, 0.0)))
        sys.exit(1)
    budget, start = Budget(args.budget_s), time.monotonic()
    skip = set(filter(None, args.skip.split(",")))
    steps: dict[str, dict] = {}
    for name, step in (
        ("tests", lambda r: step_tests(budget, r)),
        ("learner", lambda r: step_learner(budget, args.rounds, args.updates, r)),
        ("profile", lambda r: step_profile(budget, args.profile_updates, r)),
        ("up", lambda _: step_up(budget, args.up_seconds, args.port)),
    ):
        if name in skip:
            continue
        print(f"gpu-check: {name} ({budget.left():.0f} s left)", flush=True)
        try:
            steps[name] = step(reserve_after(name, skip))
        except Exception as err:  # noqa: BLE001 -- the JSON line must come, naming the step that failed
            steps[name] = {"error": f"{type(err).__name__}: {err}"}
        print(f"gpu-check: {name}: {json.dumps({k: v for k, v in steps[name].items() if k != 'tail'})}",
              flush=True)  # fmt: skip
    summary = assemble(None, steps, time.monotonic() - start)
    try:  # the check's only call into CUDA itself: a step that took the GPU down must not cost the line
        summary["gpu"] = torch.cuda.get_device_name(0)
    except Exception as err:  # noqa: BLE001
        summary |= {"ok": False, "gpu_error": f"{type(err).__name__}: {err}"[:400]}
    print(json.dumps(summary))
    sys.exit(0 if summary["ok"] else 1)


if __name__ == "__main__":
    with processes.stopped_cleanly("python -m bench.gpu"):
        main()
