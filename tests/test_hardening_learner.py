"""Issue 14, the learner's non-finite guard: a non-finite loss or gradient skips the step, a batch with
a non-finite value is dropped, weights and checkpoints are only ever finite, /status says so; a failed
checkpoint write keeps the previous one and is retried later. In process, no Zenoh."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from services.learner.core import CHECKPOINT, all_finite
from services.learner.learner import Learner
from shared import checkpoint, wire
from shared.agents.base import adam, nonfinite_skips, optimizer_step
from tests.test_learner import core_on


def _finite_params(agent) -> bool:  # noqa: ANN001
    return all_finite(agent.state_dict())


def test_a_non_finite_loss_skips_the_optimizer_step():
    layer = torch.nn.Linear(3, 1)
    opt = adam(layer.parameters(), lr=0.1)
    before = [p.detach().clone() for p in layer.parameters()]
    loss = (layer(torch.ones(1, 3)) * torch.tensor(float("nan"))).sum()
    assert optimizer_step([opt], loss).item() == 1.0
    assert all(torch.equal(a, b) for a, b in zip(before, layer.parameters(), strict=True))
    assert opt.nonfinite_skips.item() == 1
    for state in opt.state.values():  # Adam's moments never saw the NaN, and its step count stays
        assert state["step"].item() == 0
        assert not state["exp_avg"].any() and not state["exp_avg_sq"].any()
    # a finite loss whose gradient overflows is skipped too
    loss = torch.sqrt((layer.weight - layer.weight.detach()).abs()).sum()  # 0, slope infinite at 0
    assert torch.isfinite(loss)
    assert optimizer_step([opt], loss).item() == 1.0 and opt.nonfinite_skips.item() == 2
    assert optimizer_step([opt], layer(torch.ones(1, 3)).sum()).item() == 0.0
    assert not all(torch.equal(a, b) for a, b in zip(before, layer.parameters(), strict=True))
    assert all(state["step"].item() == 1 for state in opt.state.values())


def test_a_finite_step_is_the_plain_adam_step():
    """The skip costs nothing when nothing is skipped: the same weights as Adam stepped directly."""
    torch.manual_seed(0)
    layers = [torch.nn.Linear(3, 2) for _ in range(2)]
    layers[1].load_state_dict(layers[0].state_dict())
    opts = [adam(layer.parameters(), lr=0.1, weight_decay=0.01) for layer in layers]
    x = torch.randn(4, 3)
    for _ in range(3):
        optimizer_step([opts[0]], layers[0](x).pow(2).sum())
        opts[1].zero_grad()
        layers[1](x).pow(2).sum().backward()
        opts[1].step()
    assert all(torch.equal(a, b) for a, b in zip(layers[0].parameters(), layers[1].parameters(), strict=True))


def test_only_a_fused_adam_can_skip_on_the_device():
    layer = torch.nn.Linear(3, 1)
    with pytest.raises(TypeError, match="fused Adam"):
        optimizer_step([torch.optim.SGD(layer.parameters(), lr=0.1)], layer(torch.ones(1, 3)).sum())


@pytest.mark.parametrize("algo", ["nasa_td3", "sac_ae"])
def test_a_huge_reward_skips_updates_and_never_reaches_the_weights(tmp_path, algo):
    core = core_on(tmp_path, algo)
    client = core.scorer.client if core.scorer is not None else None
    batch = (client or _client()).sample(16)
    batch["reward"][:] = 3e38  # finite, but the critic's loss overflows
    core.train_on(batch)
    assert nonfinite_skips(core.agent) >= 1 and _finite_params(core.agent)
    msg = wire.decode(core.weights_message(epoch=1), wire.Weights)  # the value checks refuse NaN
    assert msg.version == core.agent.num_updates
    status = core.status("r", 1.0)
    assert status["nonfinite"]["skipped_updates"] == 1
    assert status["nonfinite"]["losses"]["critic_loss"]["last"] in ("inf", "nan")
    json.dumps(status, allow_nan=False)  # /status stays valid JSON


def _client():  # noqa: ANN202
    from shared.replay.client import LocalReplay
    from tests.test_scoring import filled_store

    return LocalReplay(filled_store(60), np.random.default_rng(0))


def test_all_finite_tells_non_finite_tensors_from_finite_ones_whose_sum_overflows():
    big = torch.full((4,), 3e38)  # finite, but its float32 sum is inf
    assert all_finite({"a": torch.ones(3), "b": {"c": big.double() * 1e100, "d": [big]}})
    assert all_finite({"steps": torch.tensor([2**62])}) and all_finite({})
    for bad in (float("nan"), float("inf"), -float("inf")):
        for dtype in (torch.float32, torch.float16, torch.bfloat16, torch.float64):
            t = torch.zeros(5, dtype=dtype)
            t[3] = bad
            assert not all_finite({"ok": torch.ones(2), "nested": {"t": t}}), (bad, dtype)
            assert not all_finite({"ok": big, "t": t}), (bad, dtype)


def test_a_batch_with_a_non_finite_value_is_dropped_with_its_rows(tmp_path):
    core = core_on(tmp_path)
    batch = core.scorer.client.sample(16)
    batch["discount"][3] = np.nan
    batch["action"][5, 0] = np.inf
    assert core.train_on(batch) == {} and core.agent.num_updates == 0
    status = core.status("r", 1.0)["nonfinite"]
    assert status["dropped_batches"] == 1
    assert status["dropped_rows"] == [int(batch["index"][3]), int(batch["index"][5])]


def test_a_dropped_batch_does_not_publish_the_same_weights_again(tmp_path):
    learner = Learner.__new__(Learner)  # publishing needs the core, the flag and the publishers
    learner.core, learner.args, learner._latest = core_on(tmp_path), SimpleNamespace(publish_every=2), {}
    learner._published, sent = None, []
    learner._publishers = {"policy": SimpleNamespace(put=sent.append)}
    learner.publish_weights()  # the loop's first publish, before any update
    for dropped in (True, False, True, False, True):
        batch = learner.core.scorer.client.sample(16)
        if dropped:
            batch["reward"][0] = np.nan
        learner.core.train_on(batch)
        learner.publish_due_weights()
    assert learner.core.agent.num_updates == 2
    versions = [wire.decode(m, wire.Weights).version for m in sent]
    assert versions == [0, 2]


def test_non_finite_weights_are_neither_published_nor_checkpointed(tmp_path):
    core = core_on(tmp_path)
    core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(60)
    assert core.save_checkpoint(wall_s=1.0)
    saved = (tmp_path / CHECKPOINT).read_bytes()
    with torch.no_grad():
        next(core.agent.actor.parameters()).fill_(float("nan"))
    assert core.weights_message(epoch=1) is None
    assert not core.save_checkpoint(wall_s=2.0) and "not finite" in core.checkpoint_error
    assert (tmp_path / CHECKPOINT).read_bytes() == saved


def test_a_failed_checkpoint_write_keeps_the_previous_and_is_retried_later(tmp_path, monkeypatch):
    core = core_on(tmp_path)
    core.board.seen_env_steps(60)
    assert core.save_checkpoint(wall_s=1.0)
    saved = (tmp_path / CHECKPOINT).read_bytes()

    def full_disk(obj, f):  # noqa: ANN001
        f.write(b"x" * 100)
        raise RuntimeError("PytorchStreamWriter failed writing file: No space left on device")

    monkeypatch.setattr(checkpoint.torch, "save", full_disk)
    core.board.seen_env_steps(10_000)
    assert core.checkpoint_due()
    assert not core.save_checkpoint(wall_s=2.0)  # no exception: the learner does not crash-loop
    assert "No space" in core.checkpoint_error and not core.checkpoint_due()  # retried later
    assert (tmp_path / CHECKPOINT).read_bytes() == saved
    assert not list((tmp_path / "learner").glob("*.tmp"))  # the torn temporary file is gone
    assert core.counters.env_steps == 60  # the counters describe the checkpoint on disk


def test_a_learner_with_a_bad_flag_exits_2_with_the_reason_before_it_connects(tmp_path):
    import os
    import subprocess
    import sys

    from nasa.up import free_port

    # No router listens there: the flag, not the connection, must be the error.
    env = {**os.environ, "NASA_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}", "NASA_RUN_ID": "bad"}
    for flag, value, reason in (("--publish-every", "0", "--publish-every must be >= 1"),
                                ("--device-prefetch", "sometimes", "--device-prefetch must be auto")):
        proc = subprocess.run([sys.executable, "-m", "services.learner", flag, value,
                               "--data", str(tmp_path), "--port", str(free_port())],
                              env=env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert reason in proc.stderr and "Traceback" not in proc.stderr
        assert not list(tmp_path.iterdir())  # refused before it locked or wrote the run folder
    # The port's environment variable, read as the flag's default, was a traceback (exit 1, restarted).
    proc = subprocess.run([sys.executable, "-m", "services.learner", "--data", str(tmp_path)],
                          env={**env, "NASA_STATUS_PORT": "80OO"}, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "NASA_STATUS_PORT='80OO' is not an integer" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(tmp_path.iterdir())
