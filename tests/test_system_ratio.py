"""Issue 14: the ratio survives a learner restart. A learner killed with SIGKILL after its checkpoint
loses the updates it made since; the restarted learner makes them up (it tells the replay's rate
limiter how many samples it has used), so the run still ends with G * (steps - warm-up) updates.
The restarted learner also replaces the last status an earlier session left with its checkpoint's."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
import torch
from system_harness import WARMUP, System

pytestmark = pytest.mark.system


@pytest.mark.timeout(500)
def test_a_learner_killed_after_its_checkpoint_makes_up_the_updates_it_lost(tmp_path):
    data, steps = tmp_path / "run", 360
    system = System(data, actors=1, steps=steps, evaluator=False,
                    extra=["--checkpoint-every", "100", "--eval-every", "100000"])
    try:
        ckpt = data / "learner" / "checkpoint.pt"
        system.wait_for("a learner checkpoint", lambda s: ckpt.exists() and s["updates"] > 0, timeout=300)
        saved = torch.load(ckpt, weights_only=True)["agent"]["num_updates"]
        before = system.wait_for("updates past the checkpoint", lambda s: s["updates"] >= saved + 20,
                                 timeout=300)
        learner = system.sup.children["learner"]
        os.kill(learner.proc.pid, signal.SIGKILL)
        lost = before["updates"] - torch.load(ckpt, weights_only=True)["agent"]["num_updates"]
        assert lost > 0  # the checkpoint holds fewer updates than the learner had made
        # A last status an earlier session left must not pass for this session's.
        saved_status = data / "learner" / "status.json"
        saved_status.write_text(json.dumps({"run_id": "an earlier session"}))
        system.wait_for("the restarted learner", lambda s: s["resumed"], timeout=300, or_run_done=True)
        assert not saved_status.exists() or "an earlier session" not in saved_status.read_text()
        deadline = time.monotonic() + 400
        while learner.exited != 0 and time.monotonic() < deadline:
            system.sup.poll(lambda msg: None)
            time.sleep(0.2)
        assert learner.restarts == 1 and learner.exited == 0, system.logs()
        final = json.loads((data / "learner" / "status.json").read_text())
        assert final["resumed"] and final["env_steps"] == steps
        # G = 1: every update the kill cost was made up, and none more
        assert final["updates"] == steps - WARMUP, system.logs()
        # With no evaluator in the run, the learner does not wait out the final evaluation's timeout.
        learner_log = (data / "logs" / "learner.log").read_text()
        assert f"no evaluator is running: eval step {steps} is left unevaluated" in learner_log, system.logs()
    finally:
        system.close()


@pytest.mark.timeout(300)
def test_a_learner_that_has_made_every_update_waits_for_the_replays_last_step_and_makes_no_more(tmp_path):
    # The replay's stats, whose `done` ends the run, come every 30 s here, and the limiter's
    # slack allows a few samples beyond G x inserts: a learner that kept drawing until it saw `done`
    # made those extra updates once it caught up with the actor's last step.
    data, steps = tmp_path / "run", 100
    system = System(data, actors=1, steps=steps, evaluator=False, extra=["--eval-every", "100000"],
                    replay_extra=["--error-buffer", "4", "--stats-every-s", "30"])
    try:
        system.wait_exit(timeout=240)
        final = json.loads((data / "learner" / "status.json").read_text())
        assert final["env_steps"] == steps
        assert final["updates"] == steps - WARMUP, system.logs()
    finally:
        system.close()


@pytest.mark.timeout(300)
def test_a_run_with_the_warm_up_burst_ends_with_as_many_updates_as_sac_aes_loop_makes(tmp_path):
    # The burst's updates (far more than the limiter's error buffer) are made at once after the
    # warm-up, the actor held back meanwhile; then G a step. The run ends with SAC-AE's count: a
    # learner aiming past it would wait forever, one the limiter held below it would end short.
    from tests.test_reference_loop import sac_ae_reference_counts

    data, steps = tmp_path / "run", 100
    system = System(data, actors=1, steps=steps, evaluator=False,
                    extra=["--eval-every", "100000", "--warmup-burst"])
    try:
        system.wait_exit(timeout=240)
        final = json.loads((data / "learner" / "status.json").read_text())
        assert final["env_steps"] == steps
        assert final["updates"] == sac_ae_reference_counts(steps, WARMUP)[-1], system.logs()
        assert final["updates_per_env_step"] == final["updates_target_per_env_step"] == 1
    finally:
        system.close()
