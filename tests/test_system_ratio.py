"""Issue 14: the ratio survives a learner restart. A learner killed with SIGKILL after its checkpoint
loses the updates it made since; the restarted learner makes them up (it tells the replay's rate
limiter how many samples it has used), so the run still ends with G * (steps - warm-up) updates."""

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
        deadline = time.monotonic() + 400
        while learner.exited != 0 and time.monotonic() < deadline:
            system.sup.poll(lambda msg: None)
            time.sleep(0.2)
        assert learner.restarts == 1 and learner.exited == 0, system.logs()
        final = json.loads((data / "learner" / "status.json").read_text())
        assert final["resumed"] and final["env_steps"] == steps
        assert final["updates"] == steps - WARMUP  # G = 1: every update the kill cost was made up
        # With no evaluator in the run, the learner does not wait out the final evaluation's timeout.
        learner_log = (data / "logs" / "learner.log").read_text()
        assert "no evaluator is running: eval step 0 is left unevaluated" in learner_log, system.logs()
    finally:
        system.close()
