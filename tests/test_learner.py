"""The learner's core without Zenoh: scoring before updates, policy lag, records, checkpoint, status."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import torch

from services.learner.core import CHECKPOINT, LearnerCore
from shared import wire
from shared.config import ConfigError
from shared.replay.client import LocalReplay
from shared.runlog import read_rows
from tests.test_scoring import filled_store
from tests.tiny import tiny_run


def core_on(tmp_path, algo: str = "nasa_td3", n: int = 60) -> LearnerCore:  # noqa: ANN001
    client = LocalReplay(filled_store(n), np.random.default_rng(0))
    return LearnerCore(tiny_run(algo, steps=200), tmp_path, client, torch.device("cpu"))


def test_an_update_scores_what_collect_timing_owes_and_reports_policy_lag(tmp_path):
    core = core_on(tmp_path)
    store = core.scorer.client.store
    for _ in range(3):
        batch = core.scorer.client.sample(16)
        metrics = core.train_on(batch)
        assert np.isfinite(batch["intrinsic"]).all()
        assert {"critic_loss", "ae_loss", "ensemble_loss"} <= set(metrics)
        assert core.last_scoring_s > 0  # the scoring's time, apart from the update's (bench.up_profile)
    assert not np.isnan(store.get(np.arange(16))["intrinsic"]).any()  # score_new wrote back the oldest rows
    status = core.status("r", 1.0)
    assert status["updates"] == 3 and status["intrinsic"]["scored"] > 0
    # The rows were collected by policy versions 0..5 (t // 10); the last update was number 2.
    assert status["policy_lag"]["max"] == 2 - int(batch["policy_version"].min())
    assert status["config_digest"] == core.run.digest()
    assert status["action_repeat"] == core.config.env.action_repeat  # what a step is, in frames


def test_an_algorithm_without_intrinsic_rewards_trains_on_unscored_rows(tmp_path):
    core = core_on(tmp_path, "td3_ae")
    assert core.scorer is None
    batch = LocalReplay(filled_store(40), np.random.default_rng(1)).sample(16)
    assert np.isnan(batch["intrinsic"]).all()
    assert "critic_loss" in core.train_on(batch)


def test_evaluations_are_recorded_once_and_episodes_carry_the_update_means(tmp_path):
    core = core_on(tmp_path)
    # The row says which weights played it: the update count the evaluator's weights carried.
    assert core.record_eval(wire.EvalResult(0, 7, [1.0, 3.0])) == {
        "step": 0, "updates": 7, "mean": 2.0, "std": 1.0, "min": 1.0, "max": 3.0,
        "return_0": 1.0, "return_1": 3.0}
    assert read_rows(tmp_path / "eval.csv")[0]["updates"] == "7"
    assert core.record_eval(wire.EvalResult(0, 0, [9.0, 9.0])) is None  # sent again after a restart
    core.train_on(core.scorer.client.sample(16))
    core.record_episode(12.5, 25, wall_s=3.0)  # no rate sampled yet: none written
    core.board.seen_env_steps(100)
    core.board.sample_rates(0)
    core.board._rates[0] = (core.board._rates[0][0] - 2.0, 60, 0)  # 40 env steps in the last 2 s
    core.record_episode(13.5, 25, wall_s=4.0)
    rows = read_rows(tmp_path / "train.csv")
    assert len(read_rows(tmp_path / "eval.csv")) == 1 and len(rows) == 2
    assert rows[0]["return"] == "12.5" and rows[0]["episode"] == "1" and rows[0]["critic_loss"] != ""
    assert rows[0]["novelty_mean"] != "" and rows[0]["steps_per_s"] == ""
    assert float(rows[1]["steps_per_s"]) == pytest.approx(20.0, rel=0.05)


def test_the_evaluators_weights_go_once_per_eval_period_with_the_decoder_and_the_actors_never_carry_it(
        tmp_path):
    core = core_on(tmp_path)  # tiny_run: eval_every 50
    decoded = lambda msg: wire.unpack_tensors(wire.decode(msg, wire.Weights).tensors)  # noqa: E731
    policy = decoded(core.weights_message(epoch=1))
    assert policy.keys() == core.agent.policy_state_dict().keys()  # the actors' weights: no decoder
    assert core.eval_weights_due()  # step 0
    at_zero = wire.decode(core.weights_message(epoch=1, evaluation=True), wire.Weights)
    assert (at_zero.version, at_zero.env_steps) == (0, 0)
    tensors = wire.unpack_tensors(at_zero.tensors)
    assert {k for k in tensors if k.startswith("decoder.")} == {
        f"decoder.{k}" for k in core.agent.decoder.state_dict()}
    assert not core.eval_weights_due()
    core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(49)
    assert not core.eval_weights_due()
    core.board.seen_env_steps(53)  # eval step 50 reached: due once, with the weights of now
    assert core.eval_weights_due()
    at_fifty = wire.decode(core.weights_message(epoch=1, evaluation=True), wire.Weights)
    assert (at_fifty.version, at_fifty.env_steps) == (1, 53)
    assert not core.eval_weights_due()
    assert "decoder.fc.weight" not in decoded(core.weights_message(epoch=1))


def test_the_budgets_own_eval_step_gets_the_weights_of_the_runs_last_update(tmp_path):
    """A budget of 230 with eval_every 50: step 230 is an eval step of its own, as in nasa train,
    and its weights go out once the run's updates (G x (230 - 225) = 5) are all made, not when the
    actors reach it; a learner that stops short (`final`) sends what it has."""
    client = LocalReplay(filled_store(60), np.random.default_rng(0))
    core = LearnerCore(tiny_run(steps=230, warmup_steps=225), tmp_path, client, torch.device("cpu"))
    assert core.target_updates == 5
    core.weights_message(epoch=1, evaluation=True)  # step 0's
    core.board.seen_env_steps(200)
    assert core.eval_weights_due()
    core.weights_message(epoch=1, evaluation=True)
    core.board.seen_env_steps(230)  # the actors are done; the learner has 5 updates to make
    assert not core.eval_weights_due()
    assert core.eval_weights_due(final=True)
    for _ in range(5):
        core.train_on(client.sample(16))
    assert core.eval_weights_due()
    final = wire.decode(core.weights_message(epoch=1, evaluation=True), wire.Weights)
    assert (final.version, final.env_steps) == (5, 230)
    assert not core.eval_weights_due(final=True)


def test_a_sac_ae_learner_aims_at_its_references_updates_and_reports_g_after_the_burst(tmp_path):
    """--algo sac_ae makes SAC-AE's warm-up burst: the learner's target is its reference's count (the
    updates its train.py has made by the run's end), and /status's ratio, without the burst's updates
    beyond G, shows G when it holds."""
    from tests.test_reference_loop import sac_ae_reference_counts

    client = LocalReplay(filled_store(60), np.random.default_rng(0))
    run = tiny_run("sac_ae", steps=230, warmup_steps=4)
    core = LearnerCore(run, tmp_path, client, torch.device("cpu"))
    warmup = run.config.warmup_steps
    assert core.target_updates == sac_ae_reference_counts(230, warmup)[-1]
    assert core.agent.burst_updates == warmup  # its actor steps by the burst's env step
    steps = warmup + 3
    for _ in range(sac_ae_reference_counts(steps, warmup)[-1]):
        core.train_on(client.sample(16))
    core.board.seen_env_steps(steps)
    assert core.status("r", 1.0)["updates_per_env_step"] == run.config.updates_per_step == 1


def test_between_updates_the_budgets_step_waits_for_the_last_update(tmp_path):
    from services.learner.evaluation import BetweenUpdates

    core = core_on(tmp_path)
    config = tiny_run(steps=230, warmup_steps=225).config
    between = BetweenUpdates(config, core.agent, done_step=200)
    assert between.due(230) is None  # 0 of its 5 updates made
    assert between.due(230, final=True) == 230
    for _ in range(5):
        core.train_on(core.scorer.client.sample(16))
    assert between.due(230) == 230


def test_a_restarted_learner_continues_from_its_checkpoint(tmp_path, monkeypatch):
    core = core_on(tmp_path)
    for _ in range(2):
        core.train_on(core.scorer.client.sample(16))
    core.weights_message(epoch=1)
    core.board.seen_env_steps(60)
    core.save_checkpoint(wall_s=4.0)
    assert (tmp_path / CHECKPOINT).exists()
    # Restarted on a host whose clock is an hour behind: its weights must still be the newest.
    stamp = wire.restart_stamp
    monkeypatch.setattr(wire, "restart_stamp", lambda per_s, bits: stamp(per_s, bits) - 3_600_000)
    again = core_on(tmp_path)
    assert again.epoch > core.epoch
    assert again.resumed and again.agent.num_updates == 2 and again.policy_version == 2
    assert again.env_steps == 60 and again.counters.wall_s == 4.0
    # An episode that ended after the checkpoint stays in train.csv: a restart numbers on from it.
    again.record_episode(10.0, 25, wall_s=6.0)
    third = core_on(tmp_path)
    third.record_episode(11.0, 25, wall_s=third.counters.wall_s + 1.0)
    rows = read_rows(tmp_path / "train.csv")
    assert [r["episode"] for r in rows] == ["1", "2"] and float(rows[1]["wall_s"]) >= 6.0
    for name, tensor in core.agent.policy_state_dict().items():
        assert torch.equal(tensor, again.agent.policy_state_dict()[name])


def test_a_refused_sample_ends_the_run_only_once_every_batch_served_is_used():
    """At the end of a run the prefetch thread asks again as soon as it has queued a batch, and the
    limiter refuses it while that batch waits: the learner must use it, not take the refusal for
    a replay that ran dry (it logged that, and resynced the limiter, at N - 1 of N updates)."""
    import time

    from services.learner.learner import ran_dry
    from shared.replay import SampleToInsertRatio
    from shared.replay.client import Prefetcher
    from shared.service import StopFlag

    limiter = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=1, error_buffer=1.0)
    limiter.restore(inserts=60, samples=57)  # three samples left in the budget
    client = LocalReplay(filled_store(60), np.random.default_rng(0), limiter)
    done_at = time.monotonic()  # the replay has said that its last env step is stored
    used = 0
    with Prefetcher(client, batch_size=8, threads=1, stop=StopFlag(), wait_s=0.01) as prefetch:
        # One batch queued and one in the thread's hands: the thread asks for the 4th, refused, once
        # the learner has taken two; the third then waits in the queue.
        for _ in range(2):
            assert prefetch.get(timeout=10.0) is not None
            used += 1
        deadline = time.monotonic() + 30.0
        while prefetch.misses == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert prefetch.misses >= 1 and prefetch.last_miss > done_at and prefetch.drawn == 3
        assert not ran_dry(done_at, prefetch.last_miss, prefetch.drawn - used)
        assert prefetch.get(timeout=10.0) is not None
        used += 1
        assert ran_dry(done_at, prefetch.last_miss, prefetch.drawn - used)
        assert prefetch.get(timeout=0.1) is None
    assert not ran_dry(None, prefetch.last_miss, 0)  # the replay still stores env steps
    assert not ran_dry(time.monotonic(), prefetch.last_miss, 0)  # no refusal since it said so


def test_the_learner_resyncs_the_limiter_again_only_after_a_resync_that_helped():
    from services.learner.learner import resync_due

    assert resync_due(8, None)  # the first shortfall
    assert resync_due(9, 8)  # the last resync let it make an update: samples may be miscounted again
    assert not resync_due(8, 8)  # the last resync brought none: the run ends short


class MiscountingReplay(LocalReplay):
    """The replay service's answers to the learner, in this process: `sync_samples` lowers the
    limiter's count as the service does, and with each draw numbered in `lost` the limiter counts
    one more sample that no update will use (a reply lost on its way, a replay restart)."""

    timeout_s = 10.0
    invalid = 0

    def __init__(self, inserts: int, lost: set[int]) -> None:
        from shared.replay import SampleToInsertRatio

        limiter = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=1, error_buffer=1.0)
        limiter.restore(inserts=inserts, samples=0)  # `inserts` samples in all
        super().__init__(filled_store(60), np.random.default_rng(0), limiter)
        self.lost, self.draws, self.synced = lost, 0, []
        self._lock = threading.Lock()

    def sample(self, batch_size: int, wait_s: float = 0.0) -> dict | None:
        with self._lock:  # the prefetch threads draw one at a time, so the draws' numbers are fixed
            batch = super().sample(batch_size, wait_s)
            if batch is not None:
                self.draws += 1
                if self.draws in self.lost:
                    assert self.limiter.take_sample(1, timeout=0.0)
            return batch

    def sync_samples(self, updates: int) -> bool:
        self.synced.append(updates)
        self.limiter.lower_samples(updates)
        return True


def end_of_run(tmp_path, client: MiscountingReplay):  # noqa: ANN001, ANN201
    """The update count a learner (td3_ae, 10 updates due) ends its loop with at the end of a run
    (the replay's last env step stored), `client` its replay."""
    from nasa.up import free_port
    from services.learner.health import LearnerArgs
    from services.learner.learner import Learner
    from shared.service import StopFlag
    from shared.zenoh_session import open_router

    run = tiny_run("td3_ae", steps=30)
    args = LearnerArgs(data=tmp_path, final_eval_wait_s=0.0, device_prefetch="off")
    with open_router(f"tcp/127.0.0.1:{free_port()}") as session:
        learner = Learner(args, session, StopFlag(), run)
        assert learner.core.target_updates == 10
        learner.client = client
        k = learner.keys
        with session.declare_publisher(k.weights) as weights, session.declare_publisher(k.eval_weights) as ev:
            learner._publishers = {"policy": weights, "evaluation": ev}
            learner.core.board.replay_stats(wire.ReplayStats(60, 0, 60, 60, 0, 0, 0, done=True))
            learner._loop()
    return learner.core.agent.num_updates


def test_a_learner_short_again_after_a_resync_that_helped_resyncs_again_and_reaches_its_target(
        tmp_path, capsys):
    """Draws 2 and 3 lost: dry at 8 of 10, resync; draw 9 lost: dry at 9, and the resync at 8
    brought an update, so another; the 10th update ends the run (one resync ended it at 9)."""
    client = MiscountingReplay(inserts=10, lost={2, 3, 9})
    assert end_of_run(tmp_path, client) == 10
    assert client.synced == [0, 8, 9]  # the start's, then one per shortfall
    log = capsys.readouterr().err
    assert "run done: " in log and "ends short" not in log


def test_a_learner_whose_resync_brought_no_update_ends_short_and_says_so(tmp_path, capsys):
    client = MiscountingReplay(inserts=8, lost=set())  # the replay allows 8 samples of the 10 due
    assert end_of_run(tmp_path, client) == 8
    assert client.synced == [0, 8]
    log = capsys.readouterr().err
    assert log.count("the run ends short: 8 of 10 updates made") == 1 and "run done: " in log


def test_batches_staged_on_the_device_train_exactly_as_host_batches(tmp_path):
    """The CUDA path's prefetcher (shared.prefetch) run on the CPU: its batches carry unscored
    (NaN) intrinsic rewards to the device; the update must use the scores computed on the host."""
    from services.learner.learner import use_device_prefetch
    from shared.prefetch import DevicePrefetcher

    torch.manual_seed(0)  # the same initial weights and update noise for both
    host = core_on(tmp_path / "host")
    for batch in [host.scorer.client.sample(16) for _ in range(3)]:
        host.train_on(batch)
    torch.manual_seed(0)
    staged = core_on(tmp_path / "staged")
    batches = [staged.scorer.client.sample(16) for _ in range(3)]
    assert np.isnan(batches[0]["intrinsic"]).any()
    queue = iter(batches)
    with DevicePrefetcher(lambda: next(queue, None), torch.device("cpu")) as prefetcher:
        for _ in range(3):
            ready = prefetcher.get(timeout=10.0)
            assert ready is not None
            staged.train_on(ready.host, ready.device)
    assert staged.agent.num_updates == host.agent.num_updates == 3
    for name, tensor in host.agent.policy_state_dict().items():
        assert torch.isfinite(tensor).all(), name
        assert torch.equal(tensor, staged.agent.policy_state_dict()[name]), name
    assert use_device_prefetch("auto", torch.device("cpu")) is False
    assert use_device_prefetch("on", torch.device("cpu")) is True
    with pytest.raises(ConfigError):
        use_device_prefetch("yes", torch.device("cpu"))


def test_the_learners_initial_weights_are_the_seeds_and_nasa_trains(tmp_path):
    from nasa.train import Trainer
    from tests.tiny import tiny_config

    torch.rand(7)  # whatever ran before in the process does not change them
    first = core_on(tmp_path / "a").agent.policy_state_dict()
    torch.rand(3)
    again = core_on(tmp_path / "b").agent.policy_state_dict()
    trainer = Trainer(tiny_config(steps=200), tmp_path / "train").agent.policy_state_dict()
    other = LearnerCore(tiny_run(steps=200, seed=1), tmp_path / "c",
                        LocalReplay(filled_store(60), np.random.default_rng(0)),
                        torch.device("cpu")).agent.policy_state_dict()
    assert first.keys() == trainer.keys()
    for name, tensor in first.items():
        assert torch.equal(tensor, again[name]) and torch.equal(tensor, trainer[name]), name
    assert any(not torch.equal(tensor, other[name]) for name, tensor in first.items())


@pytest.mark.parametrize("content", [None, b"", b"\n\n", b"\xff\xfe\n"])
def test_a_token_file_that_gives_no_token_is_refused_before_the_learner_connects(tmp_path, monkeypatch,
                                                                                 content):
    from services.learner.health import LearnerArgs
    from services.learner.learner import check_args

    monkeypatch.delenv("NASA_API_TOKEN", raising=False)
    path = tmp_path / "token"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=f"--api-token-file {path}"):
        check_args(LearnerArgs(api_token_file=path))


def bare_learner(tmp_path):  # noqa: ANN001, ANN201
    """A Learner with its core, history and status, without Zenoh: what _finish and a checkpoint use."""
    from types import SimpleNamespace

    from services.learner.health import LearnerArgs
    from services.learner.history import History
    from services.learner.learner import Learner
    from shared.service import Log, StopFlag

    learner = Learner.__new__(Learner)
    learner.core = core_on(tmp_path)
    learner.args = LearnerArgs(data=tmp_path)
    learner.keys = wire.Keys("r")
    learner.client = SimpleNamespace(invalid=0)
    learner.history, learner.log, learner.stop, learner.wall_s = History(), Log("learner"), StopFlag(), 1.0
    learner._scalars_at = 0.0
    return learner


def test_files_the_disk_refuses_at_the_end_are_logged_counted_and_the_learner_still_ends(
        tmp_path, capsys, monkeypatch):
    import builtins

    from fastapi.testclient import TestClient

    from services.learner.health import degraded_reasons
    from services.learner.learner import STATUS_FILE
    from services.learner.metrics import LearnerMetrics
    from services.learner.status_api import make_app
    from shared import files
    from tests.test_train import FullFile

    # A learner at its end, without Zenoh: what _finish uses.
    learner = bare_learner(tmp_path)
    metrics = LearnerMetrics(learner.status)
    app = make_app(learner.status, lambda: [], metrics=metrics.render,
                   degraded=lambda: degraded_reasons(learner.core), render_every_s=0.0)
    # The disk refuses the text of status.json and history.json (both go through shared.files),
    # and the last TensorBoard points.
    monkeypatch.setattr(files, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)

    def refused(*args, **kwargs):  # noqa: ANN202
        raise OSError(28, "No space left on device")

    learner.core.scalars.add({"x": 1.0}, 1)
    monkeypatch.setattr(learner.core.scalars.writer, "add_scalar", refused)
    learner._finish(finished=False)
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert learner.stop.reason == "done" and "stopping" in err
    assert "status.json not written" in err and "history.json not written" in err
    assert (tmp_path / CHECKPOINT).exists() and not (tmp_path / STATUS_FILE).exists()
    client = TestClient(app)
    writes = client.get("/status").json()["writes"]
    assert writes["failed"] == {"history.json": 1, "status.json": 1, "tensorboard": 1}
    assert writes["failing"] == ["history.json", "status.json", "tensorboard"]
    assert writes["last_error"].startswith("tensorboard: OSError")  # the last of them
    assert 'nasa_write_failures_total{file="status.json"} 1.0' in client.get("/metrics").text
    health = client.get("/healthz")
    assert health.status_code == 200 and health.text.startswith("degraded: writes failing: history.json")


def test_a_periodic_checkpoint_leaves_the_dashboard_series_a_killed_learner_resumes(tmp_path):
    from services.learner.history import load

    learner = bare_learner(tmp_path)  # what a checkpoint in the update loop uses
    for _ in range(3):
        learner.history.add(learner.status())
    learner.save_checkpoint()
    # No clean stop follows (SIGKILL): the next learner finds the checkpoint and the series beside it.
    assert (tmp_path / CHECKPOINT).exists()
    assert load(tmp_path) == learner.history.points() and len(load(tmp_path)) == 3


def test_a_periodic_checkpoint_leaves_the_status_of_that_checkpoint_for_a_killed_learner(tmp_path):
    from services.learner.learner import STATUS_FILE

    learner = bare_learner(tmp_path)  # what a checkpoint in the update loop uses
    core = learner.core

    def learn(updates: int, env_steps: int) -> None:
        for _ in range(updates):
            core.train_on(core.scorer.client.sample(16))
        core.board.seen_env_steps(env_steps)
        learner.wall_s += 1.0

    learn(2, 40)
    learner.save_checkpoint()
    # No clean stop follows (SIGKILL): `nasa status --data` reads the checkpoint's figures.
    learn(2, 50)  # after the checkpoint: not in it, nor in status.json
    saved = torch.load(tmp_path / CHECKPOINT, weights_only=True)
    status = json.loads((tmp_path / STATUS_FILE).read_text())
    assert (status["updates"], status["env_steps"], status["wall_s"]) == (2, 40, 2.0)
    assert (saved["agent"]["num_updates"], saved["env_steps"], saved["wall_s"]) == (2, 40, 2.0)
    # A checkpoint refused (a tensor not finite) leaves both as they were.
    with torch.no_grad():
        next(core.agent.actor.parameters()).fill_(float("nan"))
    learner.save_checkpoint()
    assert json.loads((tmp_path / STATUS_FILE).read_text()) == status
    assert torch.load(tmp_path / CHECKPOINT, weights_only=True)["env_steps"] == 40


def test_a_final_checkpoint_refused_leaves_the_status_of_the_last_checkpoint_written(tmp_path, capsys):
    from services.learner.learner import STATUS_FILE

    learner = bare_learner(tmp_path)
    core = learner.core
    core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(40)
    learner.save_checkpoint()
    status = json.loads((tmp_path / STATUS_FILE).read_text())
    core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(50)
    with torch.no_grad():  # the agent diverged: the stop's checkpoint is refused
        next(core.agent.actor.parameters()).fill_(float("nan"))
    learner._finish(finished=False)
    # A relaunch resumes from the checkpoint at step 40: status.json must not say 2 updates, step 50.
    assert json.loads((tmp_path / STATUS_FILE).read_text()) == status
    assert torch.load(tmp_path / CHECKPOINT, weights_only=True)["env_steps"] == 40
    err = capsys.readouterr().err
    assert "the final checkpoint was not written (a tensor is not finite)" in err
    assert "no final checkpoint" in err and "checkpoint at 2 updates" not in err


def test_a_resumed_learner_starts_with_the_status_of_its_checkpoint_and_a_fresh_one_with_none(
        tmp_path, monkeypatch):
    import builtins

    from services.learner.learner import STATUS_FILE
    from shared import files
    from tests.test_train import FullFile

    saved_status = tmp_path / STATUS_FILE
    fresh = bare_learner(tmp_path)
    saved_status.parent.mkdir(parents=True)
    saved_status.write_text(json.dumps({"run_id": "an earlier session"}))
    fresh._leave_start_status()  # no checkpoint: an earlier session's status must not pass for this one's
    assert not saved_status.exists()
    core = fresh.core
    for _ in range(2):
        core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(40)
    core.save_checkpoint(wall_s=3.0)  # and the learner is killed before it writes status.json
    again = bare_learner(tmp_path)
    assert again.core.resumed
    again._leave_start_status()  # killed again before its next checkpoint: this is what it leaves
    status = json.loads(saved_status.read_text())
    assert status["resumed"] and (status["updates"], status["env_steps"]) == (2, 40)
    assert again.status()["writes"]["failed"] == {}
    # A disk that refuses it: the earlier status goes, as for a fresh run, and the refusal is counted.
    saved_status.write_text(json.dumps({"run_id": "an earlier session"}))
    third = bare_learner(tmp_path)
    monkeypatch.setattr(files, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
    third._leave_start_status()
    monkeypatch.undo()
    assert not saved_status.exists() and third.status()["writes"]["failed"] == {"status.json": 1}


def test_a_history_the_disk_cannot_hold_leaves_no_half_written_copy(tmp_path, monkeypatch):
    import builtins

    from services.learner.history import HISTORY_FILE, History
    from shared import files
    from tests.test_train import FullFile

    History().save(tmp_path)
    before = (tmp_path / HISTORY_FILE).read_text()
    # The temporary copy is made, then the disk refuses its text.
    monkeypatch.setattr(files, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
    with pytest.raises(OSError, match="No space left"):
        History().save(tmp_path)
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "learner").iterdir()] == ["history.json"]
    assert (tmp_path / HISTORY_FILE).read_text() == before


def test_a_row_the_disk_refuses_is_dropped_and_the_learner_goes_on(tmp_path, capsys):
    import queue
    import time

    from services.learner.learner import Learner
    from shared.service import Log

    learner = Learner.__new__(Learner)  # what _drain uses, without Zenoh
    learner.core = core_on(tmp_path)
    learner.log, learner.wall_s, learner._scalars_at = Log("learner"), 1.0, time.monotonic()
    learner._evals, learner._episodes = queue.Queue(), queue.Queue()
    record_episode = learner.core.record_episode

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    learner.core.record_episode = full_disk
    learner._episodes.put((10.0, 5))
    learner._episodes.put((11.0, 5))
    learner._drain()  # no exception: the row is dropped, the loop goes on
    assert "cannot write the run folder" in capsys.readouterr().err
    learner.core.record_episode = record_episode  # room again
    learner._drain()
    assert [r["return"] for r in read_rows(tmp_path / "train.csv")] == ["11"]


def test_writes_the_disk_refuses_show_in_status_and_healthz_says_degraded(tmp_path, monkeypatch):
    import builtins
    import queue
    import time
    from types import SimpleNamespace

    from fastapi.testclient import TestClient

    from services.learner.health import LearnerArgs, degraded_reasons
    from services.learner.learner import Learner
    from services.learner.status_api import make_app
    from shared import checkpoint, runlog
    from shared.service import Log, StopFlag
    from tests.test_train import FullFile

    learner = Learner.__new__(Learner)  # what _drain, status and health use, without Zenoh
    learner.core = core_on(tmp_path)
    learner.args, learner.stop, learner.keys = LearnerArgs(data=tmp_path), StopFlag(), wire.Keys("r")
    learner.client = SimpleNamespace(invalid=0)
    learner.log, learner.wall_s, learner._scalars_at = Log("learner"), 1.0, time.monotonic()
    learner._evals, learner._episodes = queue.Queue(), queue.Queue()
    app = make_app(learner.status, learner.health, degraded=lambda: degraded_reasons(learner.core),
                   render_every_s=0.0)
    client = TestClient(app)
    assert client.get("/status").json()["writes"] == {"failed": {}, "failing": [], "last_error": "",
                                                      "last_error_at": None}
    assert client.get("/healthz").text == "ok\n"

    with monkeypatch.context() as full:  # the disk refuses the train.csv row
        full.setattr(runlog, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
        learner._episodes.put((10.0, 5))
        learner._drain()
    writes = client.get("/status").json()["writes"]
    assert writes["failed"] == {"train.csv": 1} and writes["failing"] == ["train.csv"]
    assert writes["last_error"].startswith("train.csv: OSError") and "No space" in writes["last_error"]
    assert writes["last_error_at"].endswith("Z")
    health = client.get("/healthz")
    assert health.status_code == 200 and health.text.startswith("degraded: writes failing: train.csv")

    with monkeypatch.context() as full:  # and a checkpoint
        full.setattr(checkpoint, "open", lambda *a, **k: FullFile(builtins.open(*a, **k)), raising=False)
        learner.core.board.seen_env_steps(60)
        assert not learner.core.save_checkpoint(wall_s=1.0)
    assert client.get("/status").json()["writes"]["failing"] == ["checkpoint", "train.csv"]
    health = client.get("/healthz")  # degraded, not 503: a liveness probe would restart it onto the disk
    assert health.status_code == 200 and "checkpoint, train.csv" in health.text

    learner._episodes.put((11.0, 5))  # room again: the next row goes in, the failure is history
    learner._drain()
    assert learner.core.save_checkpoint(wall_s=2.0)
    writes = client.get("/status").json()["writes"]
    assert writes["failed"] == {"checkpoint": 1, "train.csv": 1} and writes["failing"] == []
    assert client.get("/healthz").text == "ok\n"
    assert [r["return"] for r in read_rows(tmp_path / "train.csv")] == ["11"]


def test_a_tensorboard_point_the_disk_refuses_is_told_apart_from_its_csv_row(tmp_path, monkeypatch):
    import queue
    import time

    from services.learner.learner import Learner
    from shared.service import Log

    learner = Learner.__new__(Learner)
    learner.core = core_on(tmp_path)
    learner.log, learner.wall_s, learner._scalars_at = Log("learner"), 1.0, time.monotonic()
    learner._evals, learner._episodes = queue.Queue(), queue.Queue()

    def refused(*args, **kwargs):
        raise OSError(28, "No space left on device")

    learner.core.scalars.add({"x": 1.0}, 1)
    monkeypatch.setattr(learner.core.scalars.writer, "add_scalar", refused)
    learner._episodes.put((10.0, 5))
    learner._drain()
    writes = learner.core.board.snapshot()["writes"]
    assert writes["failed"] == {"tensorboard": 1} and writes["failing"] == ["tensorboard"]
    assert [r["return"] for r in read_rows(tmp_path / "train.csv")] == ["10"]  # its row went in


def test_the_intrinsic_means_and_counts_go_on_after_a_resume_and_an_older_checkpoint_still_loads(tmp_path):
    from shared import checkpoint

    core = core_on(tmp_path)
    for _ in range(2):
        core.train_on(core.scorer.client.sample(16))
    core.board.seen_env_steps(60)
    before = core.status("r", 1.0)["intrinsic"]
    assert before["scored"] > 0 and before["novelty_mean"] is not None and before["zeroed"] == 0
    assert core.save_checkpoint(wall_s=2.0)
    again = core_on(tmp_path)
    assert again.resumed and again.status("r", 2.0)["intrinsic"] == before

    state = checkpoint.load(tmp_path / CHECKPOINT)  # as a checkpoint from before they were kept
    del state["intrinsic"], state["format"]
    checkpoint.save(tmp_path / CHECKPOINT, state)
    older = core_on(tmp_path)
    assert older.resumed and older.agent.num_updates == 2
    assert older.status("r", 2.0)["intrinsic"] == {"novelty_mean": None, "surprise_mean": None, "scored": 0,
                                                   "scored_at_first_sample": 0, "zeroed": 0}


def test_scores_that_come_out_non_finite_are_stored_as_0_and_counted_in_status_and_metrics(tmp_path):
    from fastapi.testclient import TestClient

    from services.learner.metrics import LearnerMetrics
    from services.learner.status_api import make_app

    core = core_on(tmp_path)
    score, nans = core.agent.score, []

    def diverged(obs, action, next_obs):  # noqa: ANN001, ANN202 -- the first rows' scores are NaN
        scores = score(obs, action, next_obs)
        nans.append(min(2, len(obs)))
        scores["intrinsic"][:2] = float("nan")
        return scores

    core.agent.score = diverged
    batch = core.scorer.client.sample(16)
    core.train_on(batch)
    assert np.isfinite(batch["intrinsic"]).all()
    zeroed = core.status("r", 1.0)["intrinsic"]["zeroed"]
    assert zeroed == sum(nans) > 0
    store = core.scorer.client.store
    assert (store.get(np.arange(60))["intrinsic"] == 0).sum() >= zeroed  # warm-up rows and the zeroed
    status = lambda: core.status("r", 1.0)  # noqa: E731
    client = TestClient(make_app(status, lambda: [], metrics=LearnerMetrics(status).render,
                                 render_every_s=0.0))
    assert f"nasa_run_intrinsic_zeroed_transitions {float(zeroed)}" in client.get("/metrics").text
    assert core.save_checkpoint(wall_s=2.0)
    assert core_on(tmp_path).status("r", 2.0)["intrinsic"]["zeroed"] == zeroed
