"""Failures: an actor, the learner and the replay killed with SIGKILL; the supervisor restarts them."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch
from system_harness import REPO, System

from nasa.up import free_port


@pytest.mark.timeout(300)
def test_actor_learner_and_replay_survive_sigkill(tmp_path):
    data = tmp_path / "run"
    system = System(data, actors=2, steps=1_000_000, evaluator=False,
                    extra=["--checkpoint-every", "40", "--eval-every", "100000"])
    try:
        s = system.wait_for(
            "two live actors and a learner checkpoint",
            lambda s: len(s["actors"]) == 2 and all(a["alive"] for a in s["actors"]) and s["updates"] > 0
            and (data / "learner" / "checkpoint.pt").exists(),
        )
        old = {a["id"]: a["incarnation"] for a in s["actors"]}

        # An actor dies: it is seen as not alive, the other goes on, and its restart rejoins
        # with a new incarnation.
        actor0 = system.sup.children["actor-0"]
        os.kill(actor0.proc.pid, signal.SIGKILL)
        dead = system.wait_for(
            "actor 0 not alive",
            lambda s: any(a["id"] == 0 and not a["alive"] for a in s["actors"]),
            timeout=30, poll_supervisor=False,
        )
        other = next(a for a in dead["actors"] if a["id"] == 1)
        assert other["alive"]
        system.wait_for(
            "actor 1 and the learner going on",
            lambda s: s["updates"] > dead["updates"] and s["env_steps"] > dead["env_steps"]
            and next(a for a in s["actors"] if a["id"] == 1)["env_steps"] > other["env_steps"],
            poll_supervisor=False,
        )
        back = system.wait_for(
            "actor 0 back with a new incarnation",
            lambda s: any(a["id"] == 0 and a["alive"] and a["incarnation"] > old[0] and a["env_steps"] > 0
                          for a in s["actors"]),
        )
        assert actor0.restarts == 1
        assert next(a for a in back["actors"] if a["id"] == 1)["incarnation"] == old[1]

        # The learner dies: it resumes from its checkpoint; the replay kept every transition.
        learner = system.sup.children["learner"]
        before = system.status()
        os.kill(learner.proc.pid, signal.SIGKILL)
        saved = torch.load(data / "learner" / "checkpoint.pt", weights_only=True)
        resumed = system.wait_for("the learner resumed", lambda s: s["resumed"] and s["replay"]["size"] > 0)
        assert learner.restarts == 1
        assert resumed["updates"] >= saved["agent"]["num_updates"] > 0
        assert resumed["env_steps"] >= before["env_steps"]
        assert resumed["replay"]["size"] >= before["replay"]["size"]
        system.wait_for("learning to go on", lambda s: s["updates"] > resumed["updates"] + 5)

        # The replay dies: it reopens its store with every acknowledged transition (its
        # published size only counts acknowledged ones); the actors pause, abandon their
        # episodes and start new ones when it is back, and learning goes on.
        replay = system.sup.children["replay"]
        before = system.status()
        stored = before["replay"]["size"]
        os.kill(replay.proc.pid, signal.SIGKILL)
        back = system.wait_for(
            "the replay back, holding every acknowledged transition, and the actors storing again",
            lambda s: replay.restarts == 1 and s["replay"]["size"] > stored + 20,
        )
        assert back["replay"]["size"] > stored
        system.wait_for("learning to go on", lambda s: s["updates"] > back["updates"] + 5)
        actor_logs = "".join(f.read_text() for f in (data / "logs").glob("actor-*.log"))
        assert "the replay is gone" in actor_logs
        assert "no acknowledgement for 60 s" not in actor_logs
    finally:
        system.close()
    assert all(c.proc.poll() is not None for c in system.sup.children.values())
    assert system.leftover_pids() == []


@pytest.mark.timeout(240)
def test_a_second_launch_of_an_actor_id_takes_it_over_and_the_first_stops(tmp_path):
    """The same actor id started twice (a copy-pasted command, a replacement while the first was cut
    off): the replay takes only the newest incarnation's episodes, so the older process stops with
    exit code 2 and a message naming the id, is not restarted, and the run goes on with the newer."""
    data = tmp_path / "run"
    system = System(data, actors=1, steps=1_000_000, evaluator=False, extra=["--eval-every", "100000"])
    try:
        first = system.wait_for("actor 0 acting", lambda s: any(a["env_steps"] > 20 for a in s["actors"]))
        old = first["actors"][0]["incarnation"]
        original = system.sup.children["actor-0"]
        again = system.sup.add("actor-0-again", "actor", original.argv, env=original.env)
        system.wait_for("the original actor to stop for good", lambda s: original.exited is not None)
        assert original.exited == 2 and original.restarts == 0, system.logs()
        took_over = system.wait_for(
            "the second launch acting as actor 0",
            lambda s: [(a["id"], a["alive"]) for a in s["actors"]] == [(0, True)]
            and s["actors"][0]["incarnation"] > old and s["actors"][0]["env_steps"] > 20,
        )
        system.wait_for("learning to go on", lambda s: s["updates"] > took_over["updates"] + 5)
        assert again.exited is None and again.restarts == 0
        log = (data / "logs" / "actor-0.log").read_text()
        assert "actor id 0 was started again" in log and "give each actor its own --actor-id" in log
        # The newer one logs the older one's token only if it sees it before the older has gone,
        # which it may not (Zenoh's liveliness history races the older one's exit): not asserted.
    finally:
        system.close()
    assert system.leftover_pids() == []


@pytest.mark.timeout(240)
def test_a_second_replay_or_learner_of_a_run_refuses_to_serve_it(tmp_path):
    """A replay or a learner started again for a running run from another folder (another host, as far
    as file locks know): each finds its role's liveliness token up, waits out a Zenoh lease in case
    the holder just died, then exits with code 2 and says why; the run goes on."""
    data = tmp_path / "run"
    system = System(data, actors=1, steps=1_000_000, evaluator=False, extra=["--eval-every", "100000"])
    try:
        before = system.wait_for("learning", lambda s: s["updates"] > 5)
        for role in ("replay", "learner"):
            other = tmp_path / f"other-{role}"
            other.mkdir()
            shutil.copy(data / "config.json", other / "config.json")
            argv = [a.replace(str(data), str(other)) for a in system.sup.children[role].argv]
            if role == "learner":
                argv[argv.index("--port") + 1] = str(free_port())
            system.sup.add(f"{role}-again", role, argv)
        for role in ("replay", "learner"):
            again = system.sup.children[f"{role}-again"]
            system.wait_for(f"the second {role} to exit", lambda s, c=again: c.exited is not None, timeout=60)
            assert again.exited == 2 and again.restarts == 0, system.logs()
            log = (data / "logs" / f"{role}-again.log").read_text()
            assert f"{role} is served by another process already" in log, log
            assert "waiting 12 s in case its process just died" in log, log
        system.wait_for("learning to go on", lambda s: s["updates"] > before["updates"] + 20)
        assert all(system.sup.children[r].exited is None for r in ("replay", "learner", "actor-0"))
    finally:
        system.close()
    assert system.leftover_pids() == []


@pytest.mark.timeout(420)
def test_a_learner_killed_after_a_checkpoint_leaves_that_checkpoints_status_and_so_does_its_restart(tmp_path):
    # No clean stop (SIGKILL, out of memory): `nasa status --data DIR` shows the figures of the last
    # checkpoint, which the run resumes from. The next checkpoint is far off when each kill lands.
    data = tmp_path / "run"
    system = System(data, actors=1, steps=1_000_000, evaluator=False,
                    extra=["--checkpoint-every", "300", "--eval-every", "100000"])
    checkpoint, saved_status = data / "learner" / "checkpoint.pt", data / "learner" / "status.json"
    try:
        system.wait_for("a checkpoint", lambda s: checkpoint.exists(), timeout=200)
        deadline = time.monotonic() + 60
        while not saved_status.exists():  # written just after the checkpoint
            assert time.monotonic() < deadline, f"no status.json beside the checkpoint\n{system.logs()}"
            time.sleep(0.05)
        learner = system.sup.children["learner"]
        os.kill(learner.proc.pid, signal.SIGKILL)  # and not restarted: the supervisor is not polled
        learner.proc.wait()
        saved = torch.load(checkpoint, weights_only=True)
        status = json.loads(saved_status.read_text())
        out = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--data", str(data),
                              "--url", system.url], cwd=REPO, capture_output=True, text=True, timeout=60)
        # Restarted, the learner resumes from that checkpoint; killed again before its next one, it
        # still leaves that checkpoint's status, not none.
        system.wait_for("the restarted learner", lambda s: s["resumed"], timeout=200)
        os.kill(learner.proc.pid, signal.SIGKILL)
        learner.proc.wait()
        resaved = torch.load(checkpoint, weights_only=True)
        restatus = json.loads(saved_status.read_text()) if saved_status.exists() else None
        again = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--data", str(data),
                                "--url", system.url], cwd=REPO, capture_output=True, text=True, timeout=60)
    finally:
        system.close()
    assert saved["env_steps"] >= 300
    assert (status["updates"], status["env_steps"]) == (saved["agent"]["num_updates"], saved["env_steps"])
    assert out.returncode == 0, out.stderr
    assert "the learner is not running" in out.stderr
    assert json.loads(out.stdout)["env_steps"] == saved["env_steps"]
    assert restatus is not None, "the restarted learner, killed, left no status.json"
    assert restatus["resumed"]
    resumed_from = (resaved["agent"]["num_updates"], resaved["env_steps"])
    assert (restatus["updates"], restatus["env_steps"]) == resumed_from
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["env_steps"] == resaved["env_steps"]
    assert system.leftover_pids() == []
