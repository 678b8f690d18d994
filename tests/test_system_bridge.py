"""The system with its actor stepping the gripper through a robot bridge process (`nasa up --bridge`).

Real processes on loopback Zenoh, started by nasa.up's Supervisor as `nasa up` starts them:
replay, learner, one actor and its bridge. With `--bridge emulator` the bridge drives the real
servo driver and interlocks against the emulated Dynamixel bus; the bridge's safety state reaches
the learner's /status and /metrics through the actor's heartbeats. Killing the bridge pauses the
actor (no crash, no transitions) until the Supervisor restarts the bridge.
"""

from __future__ import annotations

import queue
import signal
import time
from collections.abc import Callable

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from system_harness import System

from nasa.up import bridge_id
from services.robot_bridge import operate
from shared import wire
from shared.runlog import read_rows

pytestmark = pytest.mark.system


def actor0(s: dict) -> dict:
    return s["actors"][0] if s["actors"] else {}


def metric_samples(url: str) -> dict[tuple[str, tuple], float]:
    text = httpx.get(url + "/metrics", timeout=5.0).text
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for f in text_string_to_metric_families(text) for s in f.samples}


def start(tmp_path, bridge: str, task: str, evaluator: bool = False, extra: tuple = ()) -> System:
    return System(tmp_path / "run", actors=1, steps=100_000, evaluator=evaluator,
                  extra=["--task", task, "--bridge", bridge, *extra])


def test_the_actor_steps_the_emulated_gripper_through_a_bridge_and_its_safety_state_reaches_status(tmp_path):
    system = start(tmp_path, "emulator", "gripper-valve_reset")
    try:
        s = system.wait_for("transitions through the bridge in the replay and a fault state",
                            lambda s: s["env_steps"] >= 40 and actor0(s).get("env_steps", 0) >= 40
                            and actor0(s).get("fault") == "ok", timeout=50)
        a = actor0(s)
        assert a["env_steps"] >= 40 and a["env_step_seconds"]["count"] >= 40
        got = metric_samples(system.url)
        assert got[("nasa_actor_fault_state", (("actor", "0"), ("state", "ok")))] == 1.0
        assert got[("nasa_actor_env_step_duration_seconds_count", (("actor", "0"),))] >= 40
        # The operator's e-stop: the bridge refuses, the actor pauses and says why.
        bid = bridge_id(f"t{system.port}", 0)
        ack = operate.send_estop(bid, True, "test e-stop", system.endpoint)
        # Confirmed by the bridge process `nasa up` started, with every emulated servo's torque off.
        assert ack is not None and (ack.state, ack.unreached) == ("estop", [])
        assert ack.bridge.endswith(f"pid {system.sup.children['robot_bridge-0'].proc.pid}")
        system.wait_for("the e-stop in /status", lambda s: actor0(s).get("fault") == "estop", timeout=20)
        ack = operate.send_estop(bid, False, "test re-arm", system.endpoint)
        assert ack is not None and not ack.engage
        before = system.status()["env_steps"]
        system.wait_for("collection after the re-arm",
                        lambda s: actor0(s).get("fault") == "ok" and s["env_steps"] > before, timeout=30)
    finally:
        system.close()


def test_killing_the_bridge_pauses_the_actor_and_its_restart_resumes_it(tmp_path):
    system = start(tmp_path, "stand-in", "gripper-valve")
    keys = wire.Keys(f"t{system.port}")
    beats: queue.Queue[wire.ActorStatus] = queue.Queue()
    stats: queue.Queue[wire.ReplayStats] = queue.Queue()
    # The actor's heartbeats and the replay's stats as the router (in this process) relays them:
    # each key has one sender, one session's puts, which Zenoh delivers in the order they were put,
    # so a later message on a key was sent after every earlier one and counts whatever they did.
    listen = [system.router.declare_subscriber(key, lambda s, q=q, cls=cls: q.put(
        wire.decode(s.payload.to_bytes(), cls))) for key, q, cls in (
            (keys.actor_status(0), beats, wire.ActorStatus), (keys.replay_stats, stats, wire.ReplayStats))]
    try:
        system.wait_for("steps through the bridge", lambda s: s["env_steps"] >= 30, timeout=50)
        bridge, actor = system.sup.children["robot_bridge-0"], system.sup.children["actor-0"]
        bridge.proc.send_signal(signal.SIGKILL)
        # Not polling the Supervisor: the bridge stays dead until the test lets it restart.
        lost = system.wait_for("the bridge's loss in /status",
                               lambda s: actor0(s).get("fault") == "bridge_lost", timeout=20,
                               poll_supervisor=False)
        first = next_beat(beats, lambda b: b.fault == "bridge_lost")
        # The step under way when the bridge died may still end; by the next heartbeat it has. Each
        # heartbeat after that carries the count at its sending: a step while the bridge is gone
        # would show in the last one, which arrives after all those before it.
        gone = [next_beat(beats) for _ in range(4)]
        assert actor.proc.poll() is None and actor.restarts == 0  # paused, not crashed
        assert {b.incarnation for b in gone} == {first.incarnation} == {actor0(lost)["incarnation"]}
        assert {b.fault for b in gone} == {"bridge_lost"}
        assert gone[-1].env_steps == gone[0].env_steps  # no steps while it is gone
        # The replay stores only transitions the actor stepped, so none of its stats so far counts
        # more than the actor's last heartbeat (a later stat would only count more).
        stored = [stats.get_nowait() for _ in range(stats.qsize())]
        assert stored and stored[-1].num_inserted <= gone[-1].env_steps
        # The Supervisor restarts the bridge; the same actor incarnation resumes collecting.
        resumed = system.wait_for("collection after the bridge's restart",
                                  lambda s: actor0(s).get("fault") == "ok"
                                  and s["env_steps"] > gone[-1].env_steps, timeout=50)
        assert bridge.restarts == 1 and actor0(resumed)["incarnation"] == actor0(lost)["incarnation"]
        assert actor.proc.poll() is None and actor.restarts == 0
    finally:
        for subscriber in listen:
            subscriber.undeclare()
        system.close()


def next_beat(beats: queue.Queue, pred: Callable[[wire.ActorStatus], bool] = lambda b: True,
              timeout: float = 20.0) -> wire.ActorStatus:
    """The next heartbeat that satisfies `pred` (heartbeats come each second)."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        try:
            beat = beats.get(timeout=left)
        except queue.Empty:
            break
        if pred(beat):
            return beat
    raise AssertionError(f"no such heartbeat within {timeout} s")


def test_the_evaluator_plays_its_episodes_through_a_bridge_of_its_own(tmp_path):
    system = start(tmp_path, "stand-in", "gripper-valve", evaluator=True,
                   extra=("--eval-every", "100", "--eval-episodes", "1"))
    eval_csv = tmp_path / "run" / "eval.csv"

    def evaluated(_s: dict) -> bool:
        return eval_csv.exists() and any(int(r["step"]) >= 100 for r in read_rows(eval_csv))

    try:
        system.wait_for("an evaluation after step 0", evaluated, timeout=120)
        assert "robot_bridge-eval" in system.sup.children
        assert system.sup.children["evaluator"].restarts == 0
    finally:
        system.close()
    # The evaluator has no environment of its own with --bridge: every return came through its bridge.
    log = (tmp_path / "run" / "logs" / "evaluator.log").read_text()
    assert "through bridge " + bridge_id(f"t{system.port}", "eval") in log
    rows = read_rows(eval_csv)
    assert [int(r["step"]) for r in rows][:2] == [0, 100]
    assert all(-50.0 <= float(r["mean"]) <= 0.0 for r in rows)  # 50 steps, each reward in [-1, 0]
