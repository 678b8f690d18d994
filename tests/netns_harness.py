"""Two "hosts" on one machine: network namespaces joined by a veth pair, for the multi-host test and bench.

Host A runs the router, the replay and the learner; host B runs the actors. They reach each other
only over the veth link, by link-local addresses (169.254.x.y, never routed beyond the link), so
the run's traffic crosses a real network interface that can be cut or delayed, and nothing
leaves the machine. Needs root and a kernel with network namespaces; `unavailable()` says why not.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from nasa.up import Supervisor, layout_of, parse_up, prepare, service_argv, service_command
from shared import zenoh_auth, zenoh_tls

ROUTER_PORT = 7447


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def unavailable() -> str | None:
    """Why two namespaces cannot be made here, or None when they can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"nasa-probe-{os.getpid()}"
    try:
        out = _ip("netns", "add", probe, check=False)
    except FileNotFoundError:
        return "no `ip` command (iproute2)"
    if out.returncode != 0:
        return f"`ip netns add` failed: {out.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


class TwoHosts:
    """Namespaces `a` and `b`, A at 169.254.<n>.1 and B at 169.254.<n>.2 on one veth link."""

    def __init__(self, tag: str | None = None) -> None:
        n = os.getpid() % 250 + 1
        tag = tag or str(os.getpid())
        self.ns = {"a": f"nasa-{tag}-a", "b": f"nasa-{tag}-b"}
        self.dev = {"a": f"nv{tag[-8:]}a", "b": f"nv{tag[-8:]}b"}
        self.addr = {"a": f"169.254.{n}.1", "b": f"169.254.{n}.2"}
        self.close()  # leftovers of a killed run with the same pid
        for side in "ab":
            _ip("netns", "add", self.ns[side])
        _ip("link", "add", self.dev["a"], "type", "veth", "peer", "name", self.dev["b"])
        for side in "ab":
            ns, dev = self.ns[side], self.dev[side]
            _ip("link", "set", dev, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{self.addr[side]}/30", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")

    def prefix(self, side: str) -> list[str]:
        """What runs a command on host `side`."""
        return ["ip", "netns", "exec", self.ns[side]]

    def link(self, up: bool) -> None:
        """Cut (or restore) the link at B's end, as a pulled cable or a switch going down would."""
        _ip("-n", self.ns["b"], "link", "set", self.dev["b"], "up" if up else "down")

    def delay(self, ms: float) -> None:
        """Add `ms` of delay each way (tc netem on both ends; 0 removes it). RuntimeError where the
        kernel has no netem."""
        for side in "ab":
            cmd = ["tc", "qdisc", "replace" if ms else "del", "dev", self.dev[side], "root"]
            if ms:
                cmd += ["netem", "delay", f"{ms}ms"]
            out = subprocess.run([*self.prefix(side), *cmd], capture_output=True, text=True)
            if out.returncode != 0 and ms:
                raise RuntimeError(f"tc netem is not available here: {out.stderr.strip()}")

    def close(self) -> None:
        """Remove both namespaces (their veth ends go with them)."""
        for side in "ab":
            _ip("netns", "del", self.ns[side], check=False)


class SplitSystem:
    """A run split over two hosts: router, replay and learner on A; actors on B; over TLS with
    per-role logins and the ACL (`secure`) or plain TCP. Tiny settings as tests/system_harness.py."""

    def __init__(self, hosts: TwoHosts, data: Path, actors: int = 2, secure: bool = True,
                 extra: list[str] | None = None, actor_port: int = ROUTER_PORT,
                 site_router: bool = False) -> None:
        """`actor_port`: where the actors on B connect (a relay on B's own address, as
        bench/delay_proxy.py, when not the router's port on A). `site_router`: B runs a router of
        its own that joins A's (over TLS when `secure`), and B's actors connect to it on loopback."""
        from system_harness import REPO, TINY

        self.hosts, self.data = hosts, data
        self.port = 8000
        run_id = f"mh{os.getpid()}"
        scheme = "tls" if secure else "tcp"
        self.endpoint = f"{scheme}/{hosts.addr['a']}:{ROUTER_PORT}"
        actor_endpoint = self.endpoint if actor_port == ROUTER_PORT \
            else f"{scheme}/{hosts.addr['b']}:{actor_port}"
        env = {**os.environ, "NASA_ZENOH_CONNECT": self.endpoint, "NASA_RUN_ID": run_id,
               "PYTHONPATH": str(REPO)}
        env.pop("NASA_ZENOH_AUTH", None)
        if secure:
            auth = zenoh_auth.init(data / "auth", run_id)
            zenoh_tls.init(auth, [hosts.addr["a"], hosts.addr["b"]])
            env["NASA_ZENOH_AUTH"] = str(auth)
        cmd, _ = parse_up([
            "--preset", "cpu-small", "--task", "cartpole-balance", "--algo", "nasa_td3", "--steps", "1000000",
            "--device", "cpu", "--actors", str(actors), "--port", str(self.port), "--learner-threads", "1",
            "--eval-every", "1000000", *TINY, *(extra or []),
        ])
        cmd.evaluator = False
        prepare(cmd, data)
        argv = service_argv(cmd, data, layout_of(cmd, gpu=False))
        def on(side: str) -> Callable[[str], list[str]]:
            return lambda role: [*hosts.prefix(side), *service_command(role)]

        local = f"tcp/127.0.0.1:{ROUTER_PORT}"
        envs = {"a": env, "b": {**env, "NASA_ZENOH_CONNECT": local if site_router else actor_endpoint}}
        self.sup = {side: Supervisor(envs[side], data / "logs", cwd=str(REPO), command=on(side))
                    for side in "ab"}
        self.sup["a"].add("router", "router", ["--listen", self.endpoint])
        if site_router:
            self.sup["b"].add("router-b", "router", ["--listen", local, "--join", actor_endpoint])
        for name, args in argv.items():
            self.sup["b" if name.startswith("actor") else "a"].add(name, name.split("-")[0], args)

    def status(self) -> dict | None:
        """The learner's /status, read on host A."""
        out = subprocess.run([*self.hosts.prefix("a"), "curl", "-s", "-m", "2",
                              f"http://127.0.0.1:{self.port}/status"], capture_output=True, text=True)
        try:
            return json.loads(out.stdout) if out.returncode == 0 else None
        except json.JSONDecodeError:
            return None

    def wait_for(self, what: str, pred: Callable[[dict], bool], timeout: float = 180.0,
                 seen: Callable[[dict], None] | None = None) -> dict:
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            for sup in self.sup.values():
                sup.poll(lambda msg: None)
            s = self.status()
            if s is not None:
                last = s
                if seen is not None:
                    seen(s)
                if pred(s):
                    return s
            time.sleep(0.3)
        raise AssertionError(f"timed out waiting for {what}; last status: {last}\n{self.logs()}")

    def logs(self) -> str:
        from system_harness import tail_logs

        return tail_logs(self.data / "logs")

    def restarts(self) -> dict[str, int]:
        return {c.name: c.restarts for sup in self.sup.values() for c in sup.children.values()}

    def close(self) -> None:
        try:
            self.sup["b"].stop_all(timeout_s=15.0)
        finally:
            self.sup["a"].stop_all(timeout_s=15.0)
