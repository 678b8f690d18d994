"""`python -m bench.system`: the services against the in-process loops they are built from.

- actor: env steps/s of one actor process (policy acting, streaming to a replay
  over Zenoh) against the same env + policy loop run in-process;
- actors: aggregate env steps/s with 1 and 2 actor processes;
- learner: updates/s of the learner service (batches from the replay process
  over Zenoh) against the single-process trainer's update loop (sample from
  a ReplayStore, batch_to_device, agent.update) on the same device, both with
  the same torch thread count;
- with --auth-rounds N: the one-actor and the learner figures again, with the
  router requiring each role's login and enforcing the ACL (shared/zenoh_auth)
  and without, alternating N times, and the ratios of their medians.

The replay runs without its rate limiter (--no-rate-limit) so each side is
measured at its own speed. Transitions are marked as warm-up ones (intrinsic
0), so neither learner scores intrinsic rewards here. The last line is one
JSON object. CPU load from other processes on the machine (and, for one actor,
the replay and router sharing its cores) skews wall-clock figures:
`load_avg_1m` is reported with them, and the actor's steps per CPU-second
(its own process time) next to the in-process loop's isolate its overhead.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.args import ALGOS, task_name

REPO = Path(__file__).resolve().parents[1]
# Every stored transition a warm-up one (intrinsic 0): no scoring on either side. The step budget
# (Cluster.common) is twice it, so the learner, which makes no update past G x (steps - warm-up),
# has as many to make.
WARMUP = 100_000_000
WARM = ["--warmup-steps", str(WARMUP)]
GOALS = {"actor_vs_inprocess": 0.90, "two_actor_scaling": 1.7, "learner_vs_inprocess": 0.95,
         "auth_vs_open_actor": 0.95, "auth_vs_open_learner": 0.95}


def preset_config(args: argparse.Namespace):  # noqa: ANN201
    from shared.config import default_config

    c = default_config(args.algo, "cpu-small")
    c.env.task = args.task
    c.env.render_quality = "fast"
    return c


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (Linux /proc), children excluded."""
    fields = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def inprocess_actor_loop(args: argparse.Namespace) -> tuple[float, float]:
    """The actor's loop without Zenoh: env.step + agent.act(explore=True); steps/s and steps/CPU-s."""
    import torch

    from shared import envs
    from shared.agents import make_agent
    from shared.env_loop import EnvLoop

    torch.set_num_threads(1)
    c = preset_config(args)
    env = envs.from_config(c.env, 0)
    agent = make_agent(c.algo, env.spec.obs_shape, env.spec.action_dim, c.agent, torch.device("cpu"))
    rng = np.random.default_rng(0)
    loop = EnvLoop(env)
    ts = loop.reset()
    start, cpu = time.perf_counter(), time.process_time()
    while loop.steps < 20 or time.perf_counter() - start < args.seconds:
        if loop.steps == 20:  # GL and torch warmed up: start measuring
            start, cpu = time.perf_counter(), time.process_time()
        ts = loop.step(agent.act(ts.obs, True, rng))
        if ts.last:
            ts = loop.reset()
    steps = loop.steps - 20
    return steps / (time.perf_counter() - start), steps / (time.process_time() - cpu)


def inprocess_update_loop(args: argparse.Namespace) -> float:
    """The trainer's update step: ReplayStore.sample -> batch_to_device -> agent.update, updates/s."""
    import torch

    from shared import envs
    from shared.agents import batch_to_device, make_agent
    from shared.device import resolve_device
    from shared.env_loop import EnvLoop
    from shared.replay.adder import StoreAdder
    from shared.replay.store import ReplayStore

    torch.set_num_threads(args.learner_threads)
    c = preset_config(args)
    env = envs.from_config(c.env, 0)
    spec = env.spec
    device = resolve_device(args.device)  # as `nasa train` and the learner service
    agent = make_agent(c.algo, spec.obs_shape, spec.action_dim, c.agent, device)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        store = ReplayStore(c.replay_capacity, spec.frame_shape, spec.frame_stack, spec.action_dim,
                            data_dir=Path(tmp) / "replay")
        loop = EnvLoop(env, StoreAdder(store), c.env.time_limit)
        loop.reset()
        while loop.steps < args.fill:
            if loop.step(rng.uniform(-1, 1, spec.action_dim).astype(np.float32)).last:
                loop.reset()
        n = store.num_inserted
        store.set_intrinsic(np.arange(n), np.zeros(n, np.float32))  # warm-up rows: intrinsic 0
        for _ in range(3):
            agent.update(batch_to_device(store.sample(c.batch_size, rng), device))
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < args.seconds:
            agent.update(batch_to_device(store.sample(c.batch_size, rng), device))
            n += 1
        rate = n / (time.perf_counter() - start)
        store.close()
    return rate


class Cluster:
    """A router in this process and services as child processes (nasa.up's Supervisor)."""

    def __init__(self, args: argparse.Namespace, data: Path, auth: bool = False) -> None:
        from nasa.up import Supervisor, free_port
        from shared import wire, zenoh_auth
        from shared.zenoh_session import open_client, open_router

        self.args = args
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        run_id = f"bench{free_port()}"
        # With auth, every service logs in under its role and the router enforces the run's ACL.
        folder = zenoh_auth.init(data / "auth", run_id) if auth else None
        self.router = open_router(self.endpoint, auth=folder)
        env = {**os.environ, "NASA_ZENOH_CONNECT": self.endpoint, "NASA_RUN_ID": run_id,
               "PYTHONPATH": str(REPO)}
        env.pop("NASA_ZENOH_AUTH", None)
        if folder is not None:
            env["NASA_ZENOH_AUTH"] = str(folder)
        self.sup = Supervisor(env, data / "logs", cwd=str(REPO))
        self.data = data
        self.common = ["--preset", "cpu-small", "--task", args.task, "--algo", args.algo,
                       "--render-quality", "fast", "--steps", str(2 * WARMUP)]
        self.inserted: list[tuple[float, int]] = []
        self.session = open_client(self.endpoint, role="evaluator", auth=folder)  # reads replay stats
        keys = wire.Keys(run_id)

        def on_stats(sample) -> None:  # noqa: ANN001
            s = wire.decode(sample.payload.to_bytes(), wire.ReplayStats)
            self.inserted.append((time.monotonic(), s.num_inserted))

        self.sub = self.session.declare_subscriber(keys.replay_stats, on_stats)

    def start(self, name: str, role: str, extra: list[str]) -> None:
        self.sup.add(name, role, [*self.common, *extra])

    def check_alive(self) -> None:
        """RuntimeError naming the first service that has ended, and why (its log's last line): no
        service is restarted here, and a wait on it would last its whole timeout."""
        from nasa.up import exit_text

        for child in self.sup.children.values():
            if child.proc is not None and (code := child.proc.poll()) is not None:
                raise RuntimeError(f"{child.name} {exit_text(code)} ({self.sup.last_error(child)})")

    def learner_on_a_filled_replay(self, fill: int, port: int, extra: list[str]) -> None:
        """The replay (no rate limit) filled to `fill` rows by one actor, the actor stopped, and
        the learner started on it, its status API on `port`: a learner with nothing to wait on."""
        data = str(self.data)
        self.start("replay", "replay", ["--data", data, "--no-rate-limit", *WARM])
        self.start("actor-0", "actor", ["--actor-id", "0", *WARM])
        deadline = time.monotonic() + 180
        while not (self.inserted and self.inserted[-1][1] >= fill):
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError("replay did not fill")
            time.sleep(0.2)
        actor = self.sup.children["actor-0"]
        self.sup.stopping = True
        actor.proc.terminate()
        actor.proc.wait(timeout=30)
        del self.sup.children["actor-0"]  # stopped on purpose: not a service that ended (check_alive)
        self.sup.stopping = False
        self.start("learner", "learner", ["--data", data, "--port", str(port), *extra, *WARM])

    def insert_rate(self, seconds: float, settle_s: float = 3.0, timeout: float = 120.0,
                    pids: dict[str, int] | None = None) -> tuple[float, dict[str, float]]:
        """Steps/s into the replay over `seconds`, after inserts start and `settle_s` more; and the
        CPU-seconds per step of each process in `pids` and of this one (`router`: it holds the
        router, and otherwise sleeps) over the same window."""
        pids = pids or {}
        deadline = time.monotonic() + timeout
        while not (self.inserted and self.inserted[-1][1] > 0):
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"no inserts; see {self.data / 'logs'}")
            time.sleep(0.2)
        time.sleep(settle_s)

        def cpu() -> dict[str, float]:
            return {"router": time.process_time(), **{name: cpu_seconds(pid) for name, pid in pids.items()}}

        t0, n0 = self.inserted[-1]
        c0 = cpu()
        time.sleep(seconds)
        deadline = time.monotonic() + timeout
        while self.inserted[-1][0] == t0:  # a window shorter than the replay's stats interval
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"no replay stats after the window; see {self.data / 'logs'}")
            time.sleep(0.05)
        t1, n1 = self.inserted[-1]
        c1 = cpu()
        steps = max(n1 - n0, 1)
        return (n1 - n0) / (t1 - t0), {name: (c1[name] - c0[name]) / steps for name in c0}

    def close(self) -> None:
        self.sup.stop_all(timeout_s=15.0)
        self.sub.undeclare()
        self.session.close()
        self.router.close()


def service_actor_rate(args: argparse.Namespace, actors: int,
                       auth: bool = False) -> tuple[float, dict[str, float]]:
    """Aggregate steps/s of `actors` actor processes; with one, CPU-seconds per step of the actor,
    the replay and the router (Cluster.insert_rate)."""
    with tempfile.TemporaryDirectory() as tmp:
        cluster = Cluster(args, Path(tmp), auth)
        try:
            # warm-up 0: actors act with their (initial) policy, as the in-process loop does; with no
            # learner, they do not wait for its weights
            cluster.start("replay", "replay", ["--data", tmp, "--no-rate-limit", "--warmup-steps", "0"])
            for i in range(actors):
                cluster.start(f"actor-{i}", "actor", ["--actor-id", str(i), "--warmup-steps", "0",
                                                      "--act-before-weights"])
            pids = ({name: cluster.sup.children[name].proc.pid for name in ("actor-0", "replay")}
                    if actors == 1 else {})
            return cluster.insert_rate(args.seconds, pids=pids)
        finally:
            cluster.close()


def router_round_trip(auth: bool, seconds: float, payload_bytes: int) -> tuple[float, float]:
    """Microseconds of wall and of CPU (this process: router and both clients) per round trip of
    an actor-sized insert through a router and the replay's acknowledgement back, on the run's own
    keys and roles: the router's per-message work, logins and ACL on or off, without the noise of
    rendering and learning beside it."""
    import threading

    from nasa.up import free_port
    from shared import wire, zenoh_auth
    from shared.zenoh_session import open_client, open_router

    with tempfile.TemporaryDirectory() as tmp:
        endpoint, run_id = f"tcp/127.0.0.1:{free_port()}", "benchrouter"
        folder = zenoh_auth.init(Path(tmp) / "auth", run_id) if auth else None
        keys = wire.Keys(run_id)
        got = threading.Event()
        payload, n = os.urandom(payload_bytes), 0
        with (
            open_router(endpoint, auth=folder),
            open_client(endpoint, role="actor", auth=folder) as actor,
            open_client(endpoint, role="replay", auth=folder) as replay,
            replay.declare_subscriber(keys.insert(0), lambda s: replay.put(keys.ack(0), b"ack")),
            actor.declare_subscriber(keys.ack(0), lambda s: got.set()),
        ):
            time.sleep(0.5)  # declarations propagated
            start, cpu = time.perf_counter(), time.process_time()
            while time.perf_counter() - start < seconds:
                got.clear()
                actor.put(keys.insert(0), payload)
                if not got.wait(5.0):
                    raise RuntimeError("no acknowledgement through the router in 5 s")
                n += 1
            wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    return wall / n * 1e6, cpu / n * 1e6


def service_learner_rate(args: argparse.Namespace, auth: bool = False) -> float:
    import httpx

    from nasa.up import free_port

    with tempfile.TemporaryDirectory() as tmp:
        cluster = Cluster(args, Path(tmp), auth)
        try:
            port = free_port()
            cluster.learner_on_a_filled_replay(args.fill, port, [
                "--device", args.device, "--threads", str(args.learner_threads)])
            url = f"http://127.0.0.1:{port}/status"

            def updates() -> int | None:
                try:
                    return httpx.get(url, timeout=2.0).json()["updates"]
                except (httpx.HTTPError, KeyError, ValueError):
                    return None

            deadline = time.monotonic() + 180
            while (u := updates()) is None or u < 3:
                cluster.check_alive()
                if time.monotonic() > deadline:
                    raise RuntimeError(f"learner made no updates; see {tmp}/logs")
                time.sleep(0.2)
            t0, u0 = time.monotonic(), updates()
            time.sleep(args.seconds)
            t1, u1 = time.monotonic(), updates()
            return (u1 - u0) / (t1 - t0)
        finally:
            cluster.close()


def service_figures(args: argparse.Namespace, report, load: list[float]) -> dict:  # noqa: ANN001
    """Each service against the in-process loop it is built from, and 2 actors against 1."""
    inproc_actor, inproc_cpu = inprocess_actor_loop(args)
    report("in-process env+policy steps/s", inproc_actor)
    one, one_cpu_per_step = service_actor_rate(args, 1)
    one_cpu = 1.0 / one_cpu_per_step["actor-0"] if one_cpu_per_step.get("actor-0") else None
    report("1 actor process steps/s", one)
    two = report("2 actor processes steps/s (aggregate)", service_actor_rate(args, 2)[0])
    load.append(os.getloadavg()[0])
    inproc_learner = report("in-process trainer update loop updates/s", inprocess_update_loop(args))
    service_learner = report("learner service updates/s", service_learner_rate(args))
    load.append(os.getloadavg()[0])
    return {
        "inprocess_actor_steps_per_s": round(inproc_actor, 2),
        "actor_service_steps_per_s": round(one, 2),
        "actor_vs_inprocess": round(one / inproc_actor, 3),
        "inprocess_actor_steps_per_cpu_s": round(inproc_cpu, 2),
        "actor_service_steps_per_cpu_s": round(one_cpu, 2) if one_cpu else None,
        "actor_vs_inprocess_per_cpu_s": round(one_cpu / inproc_cpu, 3) if one_cpu else None,
        "aggregate_steps_per_s_1_actor": round(one, 2),
        "aggregate_steps_per_s_2_actors": round(two, 2),
        "two_actor_scaling": round(two / one, 3),
        "inprocess_trainer_updates_per_s": round(inproc_learner, 3),
        "learner_service_updates_per_s": round(service_learner, 3),
        "learner_vs_inprocess": round(service_learner / inproc_learner, 3),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.system", description=__doc__.split("\n\n")[0])
    p.add_argument("--task", type=task_name, default="cartpole-balance")
    p.add_argument("--algo", choices=ALGOS, default="nasa_td3")
    p.add_argument("--seconds", type=float, default=10.0, help="measuring window of each figure")
    p.add_argument("--fill", type=int, default=600, help="transitions in the replay for the learner figures")
    p.add_argument("--device", default="cpu")
    p.add_argument("--learner-threads", type=int, default=1)
    p.add_argument("--auth-rounds", type=int, default=0,
                   help="also compare the actor and learner figures with Zenoh logins and the ACL on and off")
    p.add_argument("--round-trip-seconds", type=float, default=5.0,
                   help="with --auth-rounds: window of each router round-trip figure")
    p.add_argument("--round-trip-bytes", type=int, default=16384,
                   help="with --auth-rounds: size of the insert sent in the router round trip")
    p.add_argument("--only-auth", action="store_true",
                   help="with --auth-rounds: skip the in-process and scaling figures")
    args = p.parse_args(argv)

    def report(name: str, value: float) -> float:
        print(f"{name}: {value:.2f}", file=sys.stderr, flush=True)
        return value

    if args.only_auth and not args.auth_rounds:
        p.error("--only-auth needs --auth-rounds N")
    from shared.device import DeviceError, resolve_device

    try:  # here, not in the services started after the in-process figures
        resolve_device(args.device)
    except DeviceError as err:
        p.error(f"--device: {err}")
    load = [os.getloadavg()[0]]
    result: dict = {"task": args.task, "algo": args.algo, "preset": "cpu-small", "render_quality": "fast",
                    "device": args.device, "learner_threads": args.learner_threads}
    if not args.only_auth:
        result.update(service_figures(args, report, load))
    if args.auth_rounds:
        result.update(auth_comparison(args, report))
        load.append(os.getloadavg()[0])
    result["cpu_count"] = os.cpu_count()
    result["load_avg_1m"] = [round(x, 2) for x in load]
    result["goals_met"] = {k: result[k] >= v for k, v in GOALS.items() if k in result}
    print(json.dumps(result))


def auth_comparison(args: argparse.Namespace, report) -> dict:  # noqa: ANN001
    """One-actor steps/s (and CPU-seconds per step of actor, replay and router), learner updates/s,
    and the router's round trip, with the router's logins and ACL on and off, alternating (off
    first in odd rounds) so a drift of the machine's load falls on both."""
    import statistics

    parts = ("actor", "learner", "cpu_ms_per_step", "round_trip_us", "round_trip_cpu_us")
    runs: dict[bool, dict[str, list[float]]] = {on: {k: [] for k in parts} for on in (False, True)}
    for i in range(args.auth_rounds):
        for on in (False, True) if i % 2 == 0 else (True, False):
            tag = "auth" if on else "open"
            r = runs[on]
            actor, cpu = service_actor_rate(args, 1, on)
            r["actor"].append(report(f"[{tag}] 1 actor process steps/s", actor))
            r["cpu_ms_per_step"].append(report(f"[{tag}] CPU ms per env step, actor+replay+router",
                                               sum(cpu.values()) * 1e3))
            r["learner"].append(report(f"[{tag}] learner service updates/s", service_learner_rate(args, on)))
            wall_us, cpu_us = router_round_trip(on, args.round_trip_seconds, args.round_trip_bytes)
            r["round_trip_us"].append(report(f"[{tag}] router round trip, us", wall_us))
            r["round_trip_cpu_us"].append(report(f"[{tag}] router round trip, CPU us", cpu_us))
    med = {on: {k: statistics.median(v) for k, v in r.items()} for on, r in runs.items()}
    # Each round's on/off pair ran minutes apart at most: the median of their ratios is less
    # exposed to the machine's drift than the ratio of the two medians.
    paired = {k: statistics.median(on / off for on, off in zip(runs[True][k], runs[False][k], strict=True))
              for k in parts}
    return {
        "auth_rounds": args.auth_rounds,
        "open_actor_steps_per_s": [round(x, 2) for x in runs[False]["actor"]],
        "auth_actor_steps_per_s": [round(x, 2) for x in runs[True]["actor"]],
        "open_learner_updates_per_s": [round(x, 3) for x in runs[False]["learner"]],
        "auth_learner_updates_per_s": [round(x, 3) for x in runs[True]["learner"]],
        "auth_vs_open_actor": round(med[True]["actor"] / med[False]["actor"], 3),
        "auth_vs_open_learner": round(med[True]["learner"] / med[False]["learner"], 3),
        "auth_vs_open_actor_paired": round(paired["actor"], 3),
        "auth_vs_open_learner_paired": round(paired["learner"], 3),
        # CPU per env step of every process the actor's stream runs through: what logins and the
        # ACL add to the work, whatever the machine's load does to wall-clock rates.
        "open_cpu_ms_per_step": [round(x, 3) for x in runs[False]["cpu_ms_per_step"]],
        "auth_cpu_ms_per_step": [round(x, 3) for x in runs[True]["cpu_ms_per_step"]],
        "auth_vs_open_cpu_per_step_paired": round(paired["cpu_ms_per_step"], 3),
        "open_round_trip_us": [round(x, 1) for x in runs[False]["round_trip_us"]],
        "auth_round_trip_us": [round(x, 1) for x in runs[True]["round_trip_us"]],
        "auth_vs_open_round_trip_paired": round(paired["round_trip_us"], 3),
        "auth_vs_open_round_trip_cpu_paired": round(paired["round_trip_cpu_us"], 3),
        "round_trip_bytes": args.round_trip_bytes,
    }


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.system"):
        main()
