"""The system with its actor stepping the gripper through a robot bridge process (`nasa up --bridge`).

Real processes on loopback Zenoh, started by nasa.up's Supervisor as `nasa up` starts them:
replay, learner, one actor and its bridge. With `--bridge emulator` the bridge drives the real
servo driver and interlocks against the emulated Dynamixel bus; the bridge's safety state reaches
the learner's /status and /metrics through the actor's heartbeats. Killing the bridge pauses the
actor (no crash, no transitions) until the Supervisor restarts the bridge.
"""

from __future__ import annotations

import signal
import time

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from system_harness import System

from nasa.up import bridge_id
from services.robot_bridge import operate
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
    try:
        system.wait_for("steps through the bridge", lambda s: s["env_steps"] >= 30, timeout=50)
        bridge, actor = system.sup.children["robot_bridge-0"], system.sup.children["actor-0"]
        bridge.proc.send_signal(signal.SIGKILL)
        # Not polling the Supervisor: the bridge stays dead until the test lets it restart.
        lost = system.wait_for("the bridge's loss in /status",
                               lambda s: actor0(s).get("fault") == "bridge_lost", timeout=20,
                               poll_supervisor=False)
        time.sleep(2.0)  # what was sent before the loss has arrived: heartbeats and stats come each second
        settled = system.status()
        time.sleep(3.0)
        paused = system.wait_for("a fresh heartbeat", lambda s: actor0(s)["last_seen_s"] < 1.5,
                                 timeout=10, poll_supervisor=False)
        assert actor.proc.poll() is None and actor.restarts == 0  # paused, not crashed
        assert actor0(paused)["incarnation"] == actor0(lost)["incarnation"]
        assert actor0(paused)["fault"] == "bridge_lost"
        assert actor0(paused)["env_steps"] == actor0(settled)["env_steps"]  # no steps while it is gone
        assert paused["env_steps"] == settled["env_steps"]
        assert paused["replay"]["size"] == settled["replay"]["size"]
        # The Supervisor restarts the bridge; the same actor incarnation resumes collecting.
        resumed = system.wait_for("collection after the bridge's restart",
                                  lambda s: actor0(s).get("fault") == "ok"
                                  and s["env_steps"] > settled["env_steps"], timeout=50)
        assert bridge.restarts == 1 and actor0(resumed)["incarnation"] == actor0(lost)["incarnation"]
        assert actor.proc.poll() is None and actor.restarts == 0
    finally:
        system.close()


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
