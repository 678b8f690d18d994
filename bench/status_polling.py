"""`python -m bench.status_polling`: what clients polling /status and /history as fast as they are
answered cost a process that trains, with each request rendering its body (`--render-every-s 0`, as
before the shared render) and with one render a second shared by all.

One process holds a status API (uvicorn, the learner's GuardedH11Protocol) serving a learner-sized
/status, a full 1,000-point history and an eval.csv of 200 evaluations, and a training stand-in:
a small convolutional network's forward and backward passes on one torch thread, in a loop
(the learner's update is such a loop of torch calls). Windows with no client, with N pollers
(separate processes, each asking /status then /history in turn) against the API rendering
each request, and with N pollers against the API sharing one render a second, take turns, so the
drift of a shared machine's load falls on all three. Reported per kind of window: the stand-in's
steps/s, its steps per CPU-second of the whole process (the API's threads are in it), and the
requests/s answered. Each poller sends at most `--rate` requests a second (0: back to back, where
the pollers take whatever the API gives them and the requests answered are the figure). The last
line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.system import cpu_seconds

POLLER = """
import sys, time, httpx
url, pause = sys.argv[1], float(sys.argv[2])
with httpx.Client(timeout=30.0) as c:
    n = 0
    while True:
        for path in ("/status", "/history"):
            c.get(url + path)
            n += 1
            if n % 5 == 0:
                print(n, flush=True)
            time.sleep(pause)
"""


def learner_status(actors: int = 4) -> dict:
    """A /status of a learner's size (its fields as services/learner/core.py gives them)."""
    actor = {"incarnation": 1, "alive": True, "env_steps": 5000, "episodes": 5, "policy_version": 4000,
             "steps_per_s": 6.5, "last_seen_s": 0.2, "fault": None,
             "env_step_seconds": {"count": 5000, "sum": 20.5, "le": {str(b): 5000 for b in range(12)}}}
    return {
        "run_id": "bench", "algo": "nasa_td3", "task": "cartpole-balance", "device": "cpu",
        "config_digest": "0" * 16, "steps_budget": 100000, "warmup_steps": 1000, "updates": 20000,
        "updates_target_per_env_step": 1, "updates_per_env_step": 0.99, "policy_version": 20000,
        "eval": {"step": 20000, "mean": 300.5, "std": 20.25},
        "intrinsic": {"novelty_mean": 0.3, "surprise_mean": 0.01, "scored": 20000,
                      "scored_at_first_sample": 3},
        "resumed": False, "wall_s": 3600.0, "env_steps": 21000, "env_steps_per_s": 6.5, "updates_per_s": 6.4,
        "replay": {"size": 21000, "bytes": 10**9, "done": False, "dropped": 0, "invalid_messages": 0,
                   "limiter_inserts": 21000, "limiter_samples": 20000, "write_error": ""},
        "actors": [actor | {"id": i} for i in range(actors)],
        "policy_lag": {"mean": 2.5, "max": 9},
        "losses": {"critic_loss": 0.5, "actor_loss": -10.0, "ae_loss": 0.01, "ensemble_loss": 0.001},
        "nonfinite": {"skipped_updates": 0, "dropped_batches": 0, "dropped_rows": [], "losses": {}},
        "invalid_messages": 0,
        "writes": {"failed": {}, "failing": [], "last_error": "", "last_error_at": None},
    }


def trainer(stop: threading.Event, steps: list[int]) -> None:
    """The training stand-in: a small conv net's forward and backward passes, counted in `steps`."""
    import torch

    net = torch.nn.Sequential(torch.nn.Conv2d(9, 32, 3, 2), torch.nn.ReLU(), torch.nn.Conv2d(32, 32, 3),
                              torch.nn.ReLU(), torch.nn.Flatten(), torch.nn.LazyLinear(50))
    opt = torch.optim.Adam(net.parameters())
    x = torch.rand(32, 9, 48, 48)
    while not stop.is_set():
        loss = net(x).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps[0] += 1


def _count(proc: subprocess.Popen, answered: list[int], i: int) -> None:
    """A poller's running count of requests answered, into answered[i]."""
    for line in proc.stdout:  # type: ignore[union-attr]
        answered[i] = int(line)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.status_polling", description=__doc__.split("\n\n")[0])
    p.add_argument("--pollers", type=int, default=8)
    p.add_argument("--rate", type=float, default=5.0,
                   help="requests a second each poller sends at most (0: back to back)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each window")
    p.add_argument("--rounds", type=int, default=3, help="turns of the three kinds of window")
    args = p.parse_args(argv)

    import torch

    from nasa.up import free_port
    from services.learner.history import point
    from services.learner.status_api import StatusServer, make_app

    torch.set_num_threads(1)
    status = learner_status()
    points = [point(status | {"wall_s": float(i)}) for i in range(1000)]
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        rows = "".join(f"{i * 100},{i * 1.5},{i * 0.1},{i * 1.5}\n" for i in range(200))
        (data / "eval.csv").write_text("step,mean,std,return_0\n" + rows)
        servers, urls = [], {}
        for kind, every_s in (("render_each", 0.0), ("shared_render", 1.0)):
            port = free_port()
            app = make_app(lambda: status, lambda: [], lambda: points, data=data, render_every_s=every_s)
            server = StatusServer(app, "127.0.0.1", port)
            server.start()
            servers.append(server)
            urls[kind] = f"http://127.0.0.1:{port}"
        stop, steps = threading.Event(), [0]
        thread = threading.Thread(target=trainer, args=(stop, steps), daemon=True)
        thread.start()
        time.sleep(2.0)  # past the first steps' set-up
        out: dict[str, dict[str, list[float]]] = {
            k: {"steps_per_s": [], "steps_per_cpu_s": [], "requests_per_s": []}
            for k in ("quiet", "render_each", "shared_render")}
        try:
            for _ in range(args.rounds):
                for kind in out:
                    pause = 1.0 / args.rate if args.rate > 0 else 0.0
                    pollers = [subprocess.Popen([sys.executable, "-c", POLLER, urls[kind], str(pause)],
                                                stdout=subprocess.PIPE, text=True)
                               for _ in range(args.pollers if kind != "quiet" else 0)]
                    answered = [0] * len(pollers)
                    readers = [threading.Thread(target=_count, args=(q, answered, i), daemon=True)
                               for i, q in enumerate(pollers)]
                    try:
                        for r in readers:
                            r.start()
                        time.sleep(1.0)  # the pollers' start-up is not measured
                        t0, s0, c0, n0 = time.monotonic(), steps[0], cpu_seconds(os.getpid()), sum(answered)
                        time.sleep(args.seconds)
                        t1, s1, c1, n1 = time.monotonic(), steps[0], cpu_seconds(os.getpid()), sum(answered)
                    finally:  # also on Ctrl-C or SIGTERM: left, each would fail on the stopped API
                        for q in pollers:
                            q.kill()
                            q.wait()
                    out[kind]["steps_per_s"].append(round((s1 - s0) / (t1 - t0), 2))
                    out[kind]["steps_per_cpu_s"].append(round((s1 - s0) / max(c1 - c0, 1e-9), 2))
                    out[kind]["requests_per_s"].append(round((n1 - n0) / (t1 - t0), 1))
        finally:
            stop.set()
            for server in servers:
                server.stop()

    def mean(xs: list[float]) -> float:
        return round(sum(xs) / len(xs), 3) if xs else 0.0

    quiet = mean(out["quiet"]["steps_per_s"])
    result = {"windows": out,
              "steps_vs_quiet": {k: round(mean(out[k]["steps_per_s"]) / quiet, 3) for k in out},
              "requests_per_s": {k: mean(out[k]["requests_per_s"]) for k in out},
              "pollers": args.pollers, "rate": args.rate, "seconds": args.seconds, "rounds": args.rounds,
              "cpu_count": os.cpu_count(), "load_avg_1m": [round(load, 2), round(os.getloadavg()[0], 2)]}
    print(f"training steps/s against quiet: {result['steps_vs_quiet']}", file=sys.stderr)
    print(json.dumps(result))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.status_polling"):
        main()
