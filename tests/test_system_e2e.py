"""End to end: router, replay, learner, evaluator and two actors as real processes on loopback."""

from __future__ import annotations

import json

import httpx
import pytest
from system_harness import ERROR_BUFFER, WARMUP, System, assert_eval_steps

from nasa.up import other_run
from shared.runlog import read_rows

STEPS = 300
EVAL_EVERY = 100


@pytest.mark.timeout(300)
def test_system_end_to_end(tmp_path):
    # The learner stages its batches as on CUDA (shared.prefetch), so that path runs a whole run
    # here too; the other system tests run the CPU default.
    system = System(tmp_path / "run", actors=2, steps=STEPS,
                    extra=["--eval-every", str(EVAL_EVERY), "--eval-episodes", "1"],
                    learner_extra=["--device-prefetch", "on"])
    try:
        # Both actors appear and act with weights the learner published after learning started.
        s = system.wait_for(
            "both actors with learned weights",
            lambda s: len(s["actors"]) == 2
            and all(a["alive"] and a["policy_version"] > 0 for a in s["actors"]),
        )
        assert {a["id"] for a in s["actors"]} == {0, 1}
        assert all(a["env_steps"] > 0 for a in s["actors"])

        metrics = httpx.get(system.url + "/metrics", timeout=5).text
        assert "# TYPE nasa_env_steps_total counter" in metrics
        assert 'nasa_actor_alive{actor="0"} 1.0' in metrics  # the run id is in nasa_run_info only
        assert "# TYPE nasa_intrinsic_scored_transitions_total counter" in metrics
        assert 'nasa_intrinsic_mean{name="novelty"} ' in metrics
        assert httpx.get(system.url + "/healthz", timeout=5).status_code == 200
        # `nasa status --data` on this live run's folder takes this learner's status for its own.
        assert other_run(s, tmp_path / "run") is None

        # The replay holds samples (= updates) to inserts (= env steps) at G = 1 within its error buffer.
        checks = 0
        while s is not None and not s["replay"]["done"] and checks < 20:
            r = s["replay"]
            inserts, samples = r["limiter_inserts"], r["limiter_samples"]
            if inserts > WARMUP + 1:
                assert abs(samples - (inserts - WARMUP - 1)) <= ERROR_BUFFER + 2, r
                checks += 1
            s = system.wait_for("progress", lambda x, u=s["updates"]: x["updates"] > u or x["replay"]["done"],
                                or_run_done=True)
        assert checks >= 2

        # The run ends by itself (checked on the learner's last status below).
        system.wait_exit(timeout=120)
        assert all(c.exited == 0 and c.restarts == 0 for c in system.sup.children.values()), system.logs()
    finally:
        system.close()
    assert system.leftover_pids() == []

    # The learner's last status outlives it: the run ended after STEPS env steps with exactly
    # G * (STEPS - warm-up) updates, and every transition after warm-up was scored exactly once
    # (collect timing), almost all as they arrived rather than when a training batch first
    # brought them.
    final = json.loads((tmp_path / "run" / "learner" / "status.json").read_text())
    assert final["updates"] == STEPS - WARMUP and final["env_steps"] == STEPS
    intrinsic = final["intrinsic"]
    assert intrinsic["scored"] == STEPS - WARMUP and intrinsic["novelty_mean"] > 0
    assert intrinsic["scored_at_first_sample"] <= (STEPS - WARMUP) // 4, intrinsic
    assert final["invalid_messages"] == 0 and final["replay"]["invalid_messages"] == 0

    rows = read_rows(tmp_path / "run" / "eval.csv")
    assert_eval_steps([int(r["step"]) for r in rows], STEPS, EVAL_EVERY)
    assert all(r["mean"] != "" for r in rows)
    assert int(rows[-1]["updates"]) == STEPS - WARMUP  # the budget's step: the final policy's
    train = read_rows(tmp_path / "run" / "train.csv")
    assert len(train) >= 1 and all(float(r["length"]) > 0 for r in train)
    assert (tmp_path / "run" / "learner" / "checkpoint.pt").exists()
