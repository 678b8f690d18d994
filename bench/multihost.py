"""`python -m bench.multihost`: what a slow link between hosts costs a run.

The run is split over two network namespaces joined by a veth pair (tests/netns_harness.py):
router, replay and learner on host A, the actors on host B, over TLS with per-role logins
(`--plain`: TCP without logins). Each round runs it twice, with no added delay and with
`--delay-ms` each way (in alternating order), and reads the learner's /status over a window:
env steps/s (all actors) and updates/s. The delay comes from `tc netem` on both ends of the link
where the kernel has it, else from bench/delay_proxy.py on host B (`--via`); with the relay, the
no-delay runs go through it too, so only the delay differs. The rate limiter is on (G = 1), as in
a real run. Tiny settings (32 px, narrow nets) as the system tests, so the figures are the wiring's,
not the learner's arithmetic. Needs root (namespaces). The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RELAY_PORT = 7448


def netem_available() -> bool:
    """Whether this kernel has the netem qdisc (tried on a throwaway pair of namespaces)."""
    from netns_harness import TwoHosts

    hosts = TwoHosts(tag=f"nm{os.getpid()}")
    try:
        hosts.delay(1.0)
        return True
    except RuntimeError:
        return False
    finally:
        hosts.close()


def one_run(args: argparse.Namespace, delay_ms: float, via: str, round_no: int) -> dict:
    from netns_harness import SplitSystem, TwoHosts

    hosts = TwoHosts(tag=f"b{os.getpid() % 10000}{round_no}")
    relay = None
    system = None
    try:
        with tempfile.TemporaryDirectory(prefix="nasa-multihost-") as tmp:
            if via == "netem" and delay_ms:
                hosts.delay(delay_ms)
            port = RELAY_PORT if via == "relay" else 7447
            system = SplitSystem(hosts, Path(tmp) / "run", actors=args.actors, secure=not args.plain,
                                 actor_port=port)
            if via == "relay":
                relay = subprocess.Popen(
                    [*hosts.prefix("b"), sys.executable, "-m", "bench.delay_proxy",
                     "--listen", f"{hosts.addr['b']}:{RELAY_PORT}", "--to", f"{hosts.addr['a']}:7447",
                     "--delay-ms", str(delay_ms)], cwd=REPO)
            system.wait_for("every actor alive and the learner updating",
                            lambda s: len(s["actors"]) == args.actors and all(a["alive"] for a in s["actors"])
                            and s["updates"] > 20, timeout=300)
            time.sleep(args.settle)
            s0, t0 = system.status(), time.monotonic()
            time.sleep(args.seconds)
            s1, t1 = system.status(), time.monotonic()
            if s0 is None or s1 is None:
                raise RuntimeError(f"the learner's status did not answer\n{system.logs()}")
            dt = t1 - t0
            return {"delay_ms": delay_ms, "env_steps_per_s": (s1["env_steps"] - s0["env_steps"]) / dt,
                    "updates_per_s": (s1["updates"] - s0["updates"]) / dt}
    finally:
        if system is not None:
            system.close()
        if relay is not None:
            relay.terminate()
            relay.wait()
        hosts.close()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.multihost", description=__doc__.split("\n\n")[0])
    p.add_argument("--delay-ms", type=float, default=20.0, help="added each way")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seconds", type=float, default=60.0, help="measurement window of each run")
    p.add_argument("--settle", type=float, default=10.0, help="seconds after start-up before the window")
    p.add_argument("--actors", type=int, default=2)
    p.add_argument("--plain", action="store_true", help="TCP without logins instead of TLS with them")
    p.add_argument("--via", choices=("auto", "netem", "relay"), default="auto")
    args = p.parse_args(argv)
    sys.path[:0] = [str(REPO), str(REPO / "tests")]
    from netns_harness import unavailable

    if (reason := unavailable()) is not None:
        print(json.dumps({"bench": "multihost", "error": f"no network namespaces: {reason}"}))
        sys.exit(1)
    via = args.via if args.via != "auto" else ("netem" if netem_available() else "relay")
    print(f"bench.multihost: delay via {via}, {args.rounds} round(s) of {args.seconds:.0f} s windows",
          flush=True)
    runs: dict[float, list[dict]] = {0.0: [], args.delay_ms: []}
    for r in range(args.rounds):
        order = (0.0, args.delay_ms) if r % 2 == 0 else (args.delay_ms, 0.0)
        for delay in order:
            out = one_run(args, delay, via, r)
            runs[delay].append(out)
            print(json.dumps({"round": r, **out}), flush=True)

    def median(delay: float, key: str) -> float:
        return statistics.median(run[key] for run in runs[delay])

    result = {"bench": "multihost", "via": via, "secure": not args.plain, "actors": args.actors,
              "delay_ms_each_way": args.delay_ms, "rounds": args.rounds, "window_s": args.seconds,
              "load_avg_1m": os.getloadavg()[0]}
    for key in ("env_steps_per_s", "updates_per_s"):
        none, slow = median(0.0, key), median(args.delay_ms, key)
        result[f"{key}_no_delay"] = round(none, 3)
        result[f"{key}_delayed"] = round(slow, 3)
        result[f"{key}_delayed_vs_none"] = round(slow / none, 3) if none else None
    print(json.dumps(result))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.multihost"):
        main()
