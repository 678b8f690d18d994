"""`python -m bench.up_profile`: where `nasa up` spends its time on this machine.

Starts `nasa up` (its default layout for this machine unless flags after `--`
say otherwise, e.g. `-- --learner-threads 1`), waits until the learner has
made updates for --settle seconds, then over a window of --seconds measures:

- each service's CPU seconds (user + system, all its threads, from /proc) and
  its share of the machine's cores, and the launcher's (it runs the Zenoh
  router); what no service used is `unused_share_of_cores`;
- the learner's wall-clock split: updating (scoring owed rows, then the
  agent's update; the scoring's own share beside it), waiting for its next batch (the rate limiter holding it
  back, or the replay not serving in time), and the rest (draining messages,
  publishing weights, checkpoints);
- env steps/s, updates/s and updates per env step against G;
- the wire: a sampled batch's and an actor's transition batch's encoding and
  decoding, timed in this process for the run's shapes, times the window's
  counts: the CPU seconds (de)serialisation and copying cost all processes;
- with --gil, who holds the learner's interpreter lock over the window, by
  thread and by the main thread's functions (bench.gil_profile, py-spy).

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from bench.args import task_name
from bench.gil_profile import GilProfileError, Recording
from bench.processes import Drain, processes_with, stop_group, stopped_cleanly
from bench.system import cpu_seconds
from nasa.layout import usable_cores
from nasa.up import free_port
from shared.service import EXIT_BAD_INPUT, followed

REPO = Path(__file__).resolve().parents[1]


def service_pids(launcher: int) -> dict[str, int]:
    """The live services `nasa up` process `launcher` started, by module: the processes run as
    `-m services.<role>` that carry NASA_PARENT_PID. A service's own children inherit that
    variable too (the evaluator's ffmpeg, while it writes a video): they are not services."""
    found: dict[str, int] = {}
    for pid, argv in processes_with("NASA_PARENT_PID", str(launcher)):
        i = argv.index("-m") if "-m" in argv else len(argv)
        module = argv[i + 1] if i + 1 < len(argv) else ""
        if not module.startswith("services."):
            continue
        module = module.removeprefix("services.")
        name, n = module, 1
        while name in found:
            name, n = f"{module}-{n}", n + 1
        found[name] = pid
    return found


def cpu_or_nan(pid: int) -> float:
    """bench.system's cpu_seconds, NaN for a process that has gone (a restarted service)."""
    try:
        return cpu_seconds(pid)
    except OSError:
        return float("nan")


def histogram_sums(text: str) -> dict[str, tuple[float, float]]:
    """(sum, count) of each histogram in a /metrics text."""
    from prometheus_client.parser import text_string_to_metric_families

    out = {}
    for family in text_string_to_metric_families(text):
        if family.type == "histogram":
            values = {s.name: s.value for s in family.samples if not s.labels or "le" not in s.labels}
            name = family.name
            out[name] = (values.get(name + "_sum", 0.0), values.get(name + "_count", 0.0))
    return out


def snapshot(url: str, pids: dict[str, int]) -> dict:
    status = httpx.get(url + "/status", timeout=5).json()
    return {"t": time.monotonic(), "cpu": {n: cpu_or_nan(p) for n, p in pids.items()},
            "hist": histogram_sums(httpx.get(url + "/metrics", timeout=5).text),
            "env_steps": status["env_steps"], "updates": status["updates"],
            "g": status["updates_target_per_env_step"]}


def wire_seconds(run_config: Path, reps: int = 20) -> dict[str, float]:
    """CPU seconds to encode and decode one sampled batch and one actor's transition message."""
    from shared import wire
    from shared.envs import EnvSpec
    from shared.replay.client import decode_reply, encode_reply
    from shared.run_config import read_folder

    run = read_folder(run_config.parent) or {}
    spec, b = EnvSpec.from_dict(run["spec"]), int(run["batch_size"])
    c, h, w = spec.frame_shape
    rng = np.random.default_rng(0)
    sampled = {"window": rng.integers(0, 255, (b, c * (spec.frame_stack + 1), h, w), dtype=np.uint8),
               "action": rng.random((b, spec.action_dim), dtype=np.float32),
               **{k: rng.random(b, dtype=np.float32) for k in ("reward", "intrinsic", "discount")},
               "index": np.arange(b), "policy_version": np.zeros(b, dtype=np.int64)}
    start = time.process_time()
    for _ in range(reps):
        data = wire.encode(encode_reply(sampled, b))
        decode_reply(wire.decode(data, wire.SampleReply), spec)
    per_batch = (time.process_time() - start) / reps
    frame = rng.integers(0, 255, (c, h, w), dtype=np.uint8)
    start = time.process_time()
    for _ in range(reps):
        blob = wire.encode_frames(frame[None])
        wire.decode_frames(blob, 1, (c, h, w))
    return {"per_sampled_batch_s": per_batch, "per_frame_s": (time.process_time() - start) / reps,
            "batch_bytes": len(data)}


def gil_recording(pid: int | None, seconds: float, folder: Path) -> Recording | GilProfileError:
    """py-spy on the learner over the window, or why it cannot run."""
    if pid is None:
        return GilProfileError("no learner process found")
    try:
        return Recording(pid, seconds, folder / "gil.txt")
    except (GilProfileError, OSError) as err:
        return GilProfileError(str(err))


def gil_result(recording: Recording | GilProfileError) -> dict:
    """The recording's summary, or why there is none."""
    if isinstance(recording, GilProfileError):
        return {"error": str(recording)}
    try:
        return recording.result()
    except GilProfileError as err:
        return {"error": str(err)}


def wait_learning(url: str, proc: subprocess.Popen, timeout_s: float, output: Drain) -> None:
    """Until the learner has made an update; else one line: why nasa up ended (its last line of
    output), or that it made none in time."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if httpx.get(url + "/status", timeout=2).json().get("updates", 0) > 0:
                return
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(1)
    if proc.poll() is None:
        raise SystemExit(f"bench.up_profile: nasa up made no update in {timeout_s:.0f} s")
    lines = [line.strip() for line in output.lines() if line.strip()]
    why = lines[-1] if lines else "no output"
    print(f"bench.up_profile: nasa up ended (exit {proc.returncode}) before its first update: {why}",
          file=sys.stderr)
    sys.exit(2 if proc.returncode == EXIT_BAD_INPUT else 1)  # its input refused: so is this run's


def learner_wall_share(a: dict, b: dict) -> dict[str, float]:
    """The learner's wall clock between two snapshots, split by its histograms."""
    wall = b["t"] - a["t"]
    spent = {k: (b["hist"][k][0] - a["hist"].get(k, (0, 0))[0]) for k in b["hist"]}
    updating = spent.get("nasa_update_duration_seconds", 0.0)
    waiting = spent.get("nasa_batch_wait_seconds", 0.0)
    scoring = spent.get("nasa_scoring_duration_seconds", 0.0)
    return {"updating": round(updating / wall, 3), "waiting_for_batch": round(waiting / wall, 3),
            "other": round(1 - (updating + waiting) / wall, 3),
            "scoring_in_updating": round(scoring / wall, 3)}


def measure(a: dict, b: dict, wire_cost: dict, cores: int) -> dict:
    wall = b["t"] - a["t"]
    cpu = {n: round(b["cpu"][n] - a["cpu"].get(n, 0.0), 2) for n in b["cpu"]}
    updates, steps = b["updates"] - a["updates"], b["env_steps"] - a["env_steps"]
    serial = updates * wire_cost["per_sampled_batch_s"] + steps * wire_cost["per_frame_s"]
    return {
        "window_s": round(wall, 1), "cores": cores,
        "cpu_s": cpu, "cpu_share_of_cores": {n: round(v / (wall * cores), 3) for n, v in cpu.items()},
        "unused_share_of_cores": round(1 - sum(cpu.values()) / (wall * cores), 3),
        "learner_wall_share": learner_wall_share(a, b),
        "env_steps_per_s": round(steps / wall, 2), "updates_per_s": round(updates / wall, 2),
        "updates_per_env_step": round(updates / max(steps, 1), 3), "g": b["g"],
        "wire": {"per_sampled_batch_ms": round(1e3 * wire_cost["per_sampled_batch_s"], 3),
                 "per_frame_ms": round(1e3 * wire_cost["per_frame_s"], 4),
                 "sampled_batch_bytes": wire_cost["batch_bytes"],
                 "cpu_s_in_window": round(serial, 2), "share_of_cores": round(serial / (wall * cores), 4)},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", type=task_name, default="ball_in_cup-catch")
    p.add_argument("--seconds", type=float, default=120.0, help="the measured window")
    p.add_argument("--settle", type=float, default=30.0, help="seconds of learning before the window")
    p.add_argument("--gil", action="store_true",
                   help="also sample who holds the learner's interpreter lock over the window (py-spy)")
    p.add_argument("up_args", nargs="*", help="more nasa up flags, after --")
    args = p.parse_args()
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "run"
        argv = [sys.executable, "-m", "nasa.cli", "up", "--task", args.task, "--preset", "cpu-small",
                "--device", "cpu", "--data", str(data), "--port", str(port), "--router-port", "0",
                "--logs", *args.up_args]
        proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                errors="replace", start_new_session=True, env=followed())
        try:
            head = [proc.stdout.readline() for _ in range(2)]
            output = Drain(proc.stdout, head)  # read on, or nasa up stalls once the pipe is full
            layout_line = head[1].strip()
            if layout_line:  # none where nasa up refused its flags: its error comes below
                print(layout_line, flush=True)
            url = f"http://127.0.0.1:{port}"
            wait_learning(url, proc, 600, output)
            time.sleep(args.settle)
            pids = {"launcher+router": proc.pid, **service_pids(proc.pid)}
            first = snapshot(url, pids)
            recording = gil_recording(pids.get("learner"), args.seconds, Path(tmp)) if args.gil else None
            time.sleep(args.seconds)
            last = snapshot(url, pids)
            result = measure(first, last, wire_seconds(data / "config.json"), usable_cores())
            if recording is not None:
                result["learner_gil"] = gil_result(recording)
        finally:  # nasa up runs in a session of its own: only this stops it
            stop_group(proc, ((signal.SIGINT, 60.0),))
    result |= {"task": args.task, "layout": layout_line, "up_args": args.up_args,
               "load_avg_1m": round(os.getloadavg()[0], 2)}
    print(json.dumps(result))


if __name__ == "__main__":
    with stopped_cleanly("python -m bench.up_profile"):
        main()
