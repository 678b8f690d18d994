"""`python -m bench.dashboard`: what watching a run costs the learner's updates/s.

The learner service trains on a filled replay (no rate limit, no scoring, as
`bench.system`'s learner figure) while windows without any HTTP client
alternate with windows in which a client does what an open dashboard does
(/status, /history and /healthz every 2 s) plus a Prometheus scrape of
/metrics every 5 s (`--pollers N --interval 0`: N such clients, polling back to back). The
learner's logging and TensorBoard scalars are on in
both. The ratio of the polled windows' updates/s to the quiet ones' is the
cost; alternating the windows spreads the drift of a shared machine's load
over both. Updates per CPU-second of the learner process (its own time, all
its threads: the HTTP server's too) are reported beside them: other
processes' load moves them much less than wall-clock rates. The last line is
one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.args import ALGOS, task_name
from bench.system import Cluster, cpu_seconds

GOAL = 0.98  # the polled learner keeps at least 98% of its updates/s


def poll(url: str, stop: threading.Event, interval_s: float = 2.0, served: list[int] | None = None) -> None:
    """An open dashboard (every `interval_s`; 0: as fast as it is answered) and a Prometheus scrape,
    until `stop`; each request answered is counted in `served`."""
    import httpx

    with httpx.Client(timeout=5.0) as client:
        last_scrape = 0.0
        while not stop.wait(0.0):
            paths = ["/status", "/history", "/healthz"]
            if time.monotonic() - last_scrape >= 5.0:
                paths.append("/metrics")
                last_scrape = time.monotonic()
            for path in paths:
                client.get(url + path)
                if served is not None:
                    served.append(1)
            stop.wait(interval_s)


def measure(args: argparse.Namespace) -> dict:
    import httpx

    from nasa.up import free_port

    with tempfile.TemporaryDirectory() as tmp:
        cluster = Cluster(args, Path(tmp))
        try:
            port = free_port()
            cluster.learner_on_a_filled_replay(args.fill, port, ["--threads", str(args.learner_threads)])
            url = f"http://127.0.0.1:{port}"

            def updates() -> int:
                deadline = time.monotonic() + 180
                while True:
                    try:
                        return int(httpx.get(url + "/status", timeout=5.0).json()["updates"])
                    except (httpx.HTTPError, KeyError, ValueError):
                        cluster.check_alive()  # a learner that died would be waited on for ever
                        if time.monotonic() > deadline:
                            raise RuntimeError(f"no status from the learner; see {tmp}/logs") from None
                        time.sleep(0.2)

            while updates() < 3:
                time.sleep(0.5)
            pid = cluster.sup.children["learner"].proc.pid
            quiet, polled, quiet_cpu, polled_cpu, requests = [], [], [], [], []
            for _ in range(args.rounds):
                for rates, per_cpu, polling in ((quiet, quiet_cpu, False), (polled, polled_cpu, True)):
                    stop, served = threading.Event(), []
                    pollers = [threading.Thread(target=poll, args=(url, stop, args.interval, served),
                                                daemon=True) for _ in range(args.pollers if polling else 0)]
                    for poller in pollers:
                        poller.start()
                    t0, u0, c0, n0 = time.monotonic(), updates(), cpu_seconds(pid), len(served)
                    time.sleep(args.seconds)
                    t1, u1, c1, n1 = time.monotonic(), updates(), cpu_seconds(pid), len(served)
                    stop.set()
                    for poller in pollers:
                        poller.join()
                    rates.append((u1 - u0) / (t1 - t0))
                    per_cpu.append((u1 - u0) / max(c1 - c0, 1e-9))
                    if polling:
                        requests.append((n1 - n0) / (t1 - t0))
        finally:
            cluster.close()
    q, p = sum(quiet) / len(quiet), sum(polled) / len(polled)
    qc, pc = sum(quiet_cpu) / len(quiet_cpu), sum(polled_cpu) / len(polled_cpu)
    return {"quiet_updates_per_s": [round(x, 3) for x in quiet],
            "polled_updates_per_s": [round(x, 3) for x in polled],
            "quiet_updates_per_cpu_s": [round(x, 3) for x in quiet_cpu],
            "polled_updates_per_cpu_s": [round(x, 3) for x in polled_cpu],
            "polled_requests_per_s": [round(x, 1) for x in requests],
            "polled_vs_quiet": round(p / q, 3), "polled_vs_quiet_per_cpu_s": round(pc / qc, 3),
            "goal": GOAL, "goal_met": {"wall_clock": p / q >= GOAL, "per_cpu_s": pc / qc >= GOAL}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.dashboard", description=__doc__.split("\n\n")[0])
    p.add_argument("--task", type=task_name, default="cartpole-balance")
    p.add_argument("--algo", choices=ALGOS, default="nasa_td3")
    p.add_argument("--seconds", type=float, default=15.0, help="length of each window")
    p.add_argument("--rounds", type=int, default=2, help="pairs of quiet and polled windows")
    p.add_argument("--fill", type=int, default=600, help="transitions stored before the learner starts")
    p.add_argument("--learner-threads", type=int, default=1)
    p.add_argument("--pollers", type=int, default=1, help="clients polling at once in a polled window")
    p.add_argument("--interval", type=float, default=2.0,
                   help="seconds between a poller's rounds of /status, /history, /healthz (0: back to back)")
    args = p.parse_args(argv)
    load = os.getloadavg()[0]
    result = measure(args)
    result |= {"task": args.task, "algo": args.algo, "preset": "cpu-small", "cpu_count": os.cpu_count(),
               "pollers": args.pollers, "interval_s": args.interval,
               "load_avg_1m": [round(load, 2), round(os.getloadavg()[0], 2)]}
    print(f"polled / quiet updates/s: {result['polled_vs_quiet']}, per learner CPU-second: "
          f"{result['polled_vs_quiet_per_cpu_s']}", file=sys.stderr)
    print(json.dumps(result))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.dashboard"):
        main()
