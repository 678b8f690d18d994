"""`python -m bench.faults`: the system's speed under a steady stream of bad messages (issue 14).

A system of real processes on loopback (tests/system_harness.py: tiny settings, G = 1, no evaluator)
runs a warm-up, then `--rounds` pairs of phases of `--seconds` each, clean then under fuzz
(alternating, so a change in the machine's load falls on both alike). Under fuzz a thread sends
`--rate` messages per second, spread over every key of shared/wire.py, each one a message the receiver's
value checks refuse (tests/test_fuzz.py's variants, without the giant payloads). It reports env
steps/s and updates/s of the clean and the fuzzed phases (from /status), the fuzzed fraction of
the clean figures, and the services' restarts. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GOAL = 0.90
MAX_PAYLOAD = 64 << 10


def bad_messages(keys, spec) -> list[tuple[str, str, bytes]]:  # noqa: ANN001
    """(put or get, key, payload) of every refused variant up to MAX_PAYLOAD bytes, keys interleaved."""
    import test_fuzz as fz

    from shared import wire

    bounds = wire.Bounds.of(spec)
    valid = fz.valid_messages(spec)
    targets = {
        wire.TransitionBatch: ("put", keys.insert(fz.FAKE_ACTOR)), wire.InsertAck: ("put", keys.ack(0)),
        wire.SampleRequest: ("get", keys.sample), wire.UnscoredRequest: ("get", keys.unscored),
        wire.SetIntrinsic: ("put", keys.intrinsic), wire.ReplayStats: ("put", keys.replay_stats),
        wire.Weights: ("put", keys.weights), wire.ActorStatus: ("put", keys.actor_status(fz.FAKE_ACTOR)),
        wire.EvalResult: ("put", keys.eval_result), wire.Stop: ("put", keys.stop),
    }
    per_key = [[(how, key, p) for p in fz.variants(valid[cls])
                if len(p) <= MAX_PAYLOAD and fz.refused(p, cls, bounds)]
               for cls, (how, key) in targets.items()]
    return [m for group in itertools.zip_longest(*per_key) for m in group if m is not None]


def fuzz_stream(session, messages: list, rate: float, stop: threading.Event, sent: list) -> None:  # noqa: ANN001
    import zenoh

    block = zenoh.CongestionControl.BLOCK
    start = time.monotonic()
    for i, (how, key, payload) in enumerate(itertools.cycle(messages)):
        if stop.is_set():
            return
        if how == "put":
            session.put(key, payload, congestion_control=block)
        else:
            session.get(key, payload=payload, timeout=1.0)  # the replies are not read
        sent[0] += 1
        delay = start + (i + 1) / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def phase(system, seconds: float) -> tuple[float, int, int]:  # noqa: ANN001
    """(seconds, env steps, updates) of one phase."""
    a = system.status()
    time.sleep(seconds)
    b = system.status()
    return b["wall_s"] - a["wall_s"], b["env_steps"] - a["env_steps"], b["updates"] - a["updates"]


def fuzzed_phase(system, session, messages: list, rate: float, seconds: float,  # noqa: ANN001
                 sent: list) -> tuple[float, int, int]:
    """One phase (`phase`) under a stream of bad messages, stopped with it however it ends: left
    running, the sender (not a daemon) would keep this process from exiting after a Ctrl-C."""
    stop = threading.Event()
    sender = threading.Thread(target=fuzz_stream, args=(session, messages, rate, stop, sent))
    sender.start()
    try:
        return phase(system, seconds)
    finally:
        stop.set()
        sender.join()


def rates(phases: list[tuple[float, int, int]]) -> dict:
    t, e, u = (sum(p[i] for p in phases) for i in range(3))
    return {"env_steps_per_s": round(e / t, 2), "updates_per_s": round(u / t, 2), "seconds": round(t, 1)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=15.0, help="length of each phase")
    p.add_argument("--rounds", type=int, default=4, help="clean and fuzzed phase pairs")
    p.add_argument("--rate", type=float, default=200.0, help="bad messages per second under fuzz")
    p.add_argument("--actors", type=int, default=1)
    args = p.parse_args(argv)
    sys.path[:0] = [str(REPO), str(REPO / "tests")]
    import zenoh
    from system_harness import System
    from test_fuzz import _client_config

    from shared import wire
    from shared.envs import EnvSpec
    from shared.run_config import read_folder

    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "run"
        system = System(data, actors=args.actors, steps=10**8, evaluator=False,
                        extra=["--eval-every", "10000000", "--checkpoint-every", "10000000"])
        try:
            s = system.wait_for("learning", lambda s: s["updates"] > 20, timeout=300)
            spec = EnvSpec.from_dict(read_folder(data)["spec"])
            session = zenoh.open(_client_config(system.endpoint))
            messages = bad_messages(wire.Keys(s["run_id"]), spec)
            phase(system, args.seconds)  # warm-up: the first updates and batches are slower
            clean, fuzzed, sent = [], [], [0]
            for _ in range(args.rounds):
                clean.append(phase(system, args.seconds))
                fuzzed.append(fuzzed_phase(system, session, messages, args.rate, args.seconds, sent))
            last = system.status()
            restarts = sum(c.restarts for c in system.sup.children.values())
            session.close()
        finally:
            system.close()
    clean, fuzzed = rates(clean), rates(fuzzed)
    keys = ("env_steps_per_s", "updates_per_s")
    result = {
        "clean": clean, "fuzzed": fuzzed,
        "fuzzed_vs_clean": {k: round(fuzzed[k] / clean[k], 3) if clean[k] else None for k in keys},
        "bad_messages_sent": sent[0], "distinct_bad_messages": len(messages), "rate": args.rate,
        "invalid_learner": last["invalid_messages"], "invalid_replay": last["replay"]["invalid_messages"],
        "restarts": restarts, "goal": GOAL, "load_avg_1m": round(os.getloadavg()[0], 2),
    }
    fractions = result["fuzzed_vs_clean"].values()
    result["ok"] = restarts == 0 and all(v is not None and v >= GOAL for v in fractions)
    print(json.dumps(result))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.faults"):
        main()
