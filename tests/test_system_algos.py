"""Each baseline through the whole distributed system: the end-to-end test runs nasa_td3 only, and a
part that reads an agent's modules (the evaluator's pictures, the learner's weights) can hold for
one algorithm and fail for another."""

from __future__ import annotations

import json

import pytest
from system_harness import System

from shared.runlog import read_rows

STEPS = 80
EVAL_EVERY = 40


@pytest.mark.timeout(300)
@pytest.mark.parametrize("algo", ["td3_ae", "pixel_td3", "sac_ae"])
def test_each_baseline_runs_to_its_end_with_evaluations_and_no_service_restarted(tmp_path, algo):
    data = tmp_path / "run"
    system = System(data, actors=1, steps=STEPS,
                    extra=["--algo", algo, "--eval-every", str(EVAL_EVERY), "--eval-episodes", "1"])
    try:
        system.wait_exit(timeout=240)
        ended = {c.name: (c.exited, c.restarts) for c in system.sup.children.values()}
        assert all(e == (0, 0) for e in ended.values()), f"{ended}\n{system.logs()}"
    finally:
        system.close()
    assert json.loads((data / "config.json").read_text())["algo"] == algo
    steps = [int(r["step"]) for r in read_rows(data / "eval.csv")]
    assert steps[0] == 0 and steps[-1] == STEPS, steps
    # The pictures of each evaluation: a video, and the autoencoder's view for those that have an
    # autoencoder (SAC-AE's decoder reads its critic's encoder, which its policy does not use).
    media = json.loads((data / "media" / "media.json").read_text())
    assert media["videos"], media
    assert (media["autoencoder"] is not None) == (algo != "pixel_td3"), media
