"""Collect-timing scoring over the in-process replay client: warm-up zeros, once per row, write-back."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

from shared import wire
from shared.agents import make_agent
from shared.replay.adder import StoreAdder
from shared.replay.client import LocalReplay
from shared.replay.store import ReplayStore
from shared.scoring import IntrinsicScorer
from tests.tiny import WARMUP, tiny_run


def filled_store(n: int, seed: int = 0) -> ReplayStore:
    """n transitions of random frames in episodes of 25 steps."""
    spec = tiny_run().spec
    rng = np.random.default_rng(seed)
    store = ReplayStore(1000, spec.frame_shape, spec.frame_stack, spec.action_dim)
    adder = StoreAdder(store)
    for t in range(n):
        if t % 25 == 0:
            adder.add_first(rng.integers(0, 255, spec.frame_shape, np.uint8))
        frame = rng.integers(0, 255, spec.frame_shape, np.uint8)
        adder.add(rng.uniform(-1, 1, spec.action_dim).astype(np.float32), 1.0, 1.0, frame,
                  t % 25 == 24, policy_version=t // 10)
    return store


def nasa_agent():  # noqa: ANN201
    run = tiny_run()
    torch.manual_seed(0)
    spec = run.spec
    return make_agent("nasa_td3", spec.obs_shape, spec.action_dim, run.config.agent, torch.device("cpu"))


class LossyClient(LocalReplay):
    """Write-backs are lost (a replay restart between scoring and storing)."""

    def set_intrinsic(self, index: np.ndarray, values: np.ndarray) -> None:
        pass


def test_warmup_rows_score_zero_later_rows_once_each_and_the_store_holds_the_scores():
    store, agent = filled_store(60), nasa_agent()
    client = LocalReplay(store, np.random.default_rng(0))
    scorer = IntrinsicScorer(agent, client, WARMUP, batch_size=16)
    scorer.catch_up()
    stored = store.get(np.arange(60))["intrinsic"]
    assert np.all(stored[:WARMUP] == 0.0)
    assert scorer.scored == 60 - WARMUP and scorer.scored_at_first_sample == 0
    rows = store.get(np.arange(WARMUP, 60))
    expected = agent.score(torch.as_tensor(rows["obs"]), torch.as_tensor(rows["action"]),
                           torch.as_tensor(rows["next_obs"]))["intrinsic"].numpy()
    np.testing.assert_allclose(stored[WARMUP:], expected, rtol=1e-5, atol=1e-6)
    assert scorer.score_new() == 0  # nothing left: no row is scored twice
    assert scorer.scored == 60 - WARMUP


def test_a_training_batch_with_unscored_rows_is_filled_in_place_once_per_distinct_row():
    store, agent = filled_store(40), nasa_agent()
    client = LocalReplay(store, np.random.default_rng(0))
    scorer = IntrinsicScorer(agent, client, WARMUP, batch_size=16)
    batch = client.store.get(np.array([5, 30, 30, 31, 5]))
    batch = {k: batch[k] for k in ("obs", "next_obs", "action", "intrinsic", "index")}
    assert np.isnan(batch["intrinsic"]).all()
    scorer.score_batch(batch)
    values = batch["intrinsic"]
    assert values[0] == 0.0 and values[4] == 0.0  # warm-up row
    assert values[1] == values[2] and np.isfinite(values).all()
    assert scorer.scored == 2 and scorer.scored_at_first_sample == 2  # rows 30 and 31
    np.testing.assert_array_equal(store.get(np.array([5, 30, 31]))["intrinsic"], values[[0, 1, 3]])


def test_a_lost_write_back_returns_the_first_score_not_a_second_one():
    store, agent = filled_store(40), nasa_agent()
    scorer = IntrinsicScorer(agent, LossyClient(store, np.random.default_rng(0)), WARMUP, batch_size=8)
    scorer.score_new()  # rows 0..7: warm-up
    first = {k: v for k, v in store.get(np.arange(30, 34)).items()}
    scorer.score_batch(first)
    scored = scorer.scored
    with torch.no_grad():  # the networks change: a second computation would differ
        for p in agent.decoder.parameters():
            p.add_(0.5)
    again = store.get(np.arange(30, 34))
    assert np.isnan(again["intrinsic"]).all()  # the write-back never landed
    scorer.score_batch(again)
    np.testing.assert_array_equal(again["intrinsic"], first["intrinsic"])
    assert scorer.scored == scored


def test_a_score_that_is_not_finite_or_beyond_the_replays_bound_is_stored_as_zero_or_clipped():
    """The replay refuses a non-finite or out-of-bound score (the in-process store raises), and
    the update must not train on one: the stored, cached and accounted score is bounded."""
    store, agent = filled_store(40), nasa_agent()
    scorer = IntrinsicScorer(agent, LocalReplay(store, np.random.default_rng(0)), WARMUP, batch_size=16)
    bound = wire.Bounds.max_abs_reward  # what a replay accepts unless told less
    real = agent.score

    def diverged(obs, action, next_obs):  # noqa: ANN001, ANN202
        scores = {k: v.clone() for k, v in real(obs, action, next_obs).items()}
        for v in scores.values():
            v[0], v[1], v[2] = float("nan"), float("inf"), 10 * bound
        return scores

    agent.score = diverged
    batch = store.get(np.arange(30, 34))
    scorer.score_batch(batch)
    np.testing.assert_array_equal(batch["intrinsic"][:3], [0.0, 0.0, bound])
    np.testing.assert_array_equal(store.get(np.arange(30, 34))["intrinsic"], batch["intrinsic"])
    assert [scorer._cache[i] for i in (30, 31, 32)] == [0.0, 0.0, bound]
    assert np.isfinite([scorer.means["novelty"], scorer.means["surprise"]]).all()


def test_episode_means_are_per_scored_transition_and_reset_when_taken():
    store, agent = filled_store(60), nasa_agent()
    scorer = IntrinsicScorer(agent, LocalReplay(store, np.random.default_rng(0)), WARMUP, batch_size=16)
    assert scorer.take_episode_means() == {}
    scorer.catch_up()
    means = scorer.take_episode_means()
    assert set(means) == {"novelty_mean", "surprise_mean"}
    assert means["novelty_mean"] == pytest.approx(scorer.means["novelty"])
    assert scorer.take_episode_means() == {}


def test_a_scorer_started_late_zeroes_the_warm_up_and_scores_the_new_row_in_the_same_call():
    """A resumed run: the first call must also score the newest row, before the next update."""
    store, agent = filled_store(40), nasa_agent()
    client = LocalReplay(store, np.random.default_rng(0))
    client.set_intrinsic(np.arange(39), np.full(39, 0.5, np.float32))  # all but the row added last
    late = IntrinsicScorer(agent, client, WARMUP, batch_size=64)
    late.score_new()
    assert not np.isnan(store.get(np.arange(40))["intrinsic"]).any()
    assert late.scored == 1


class CountingClient(LocalReplay):
    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self.scans = 0

    def unscored(self, after: int, limit: int):  # noqa: ANN201
        self.scans += 1
        return super().unscored(after, limit)


def test_the_scorer_asks_the_replay_only_when_rows_were_stored_since_its_last_scan():
    store, agent = filled_store(40), nasa_agent()
    client = CountingClient(store, np.random.default_rng(0))
    scorer = IntrinsicScorer(agent, client, WARMUP, batch_size=64)
    scorer.catch_up()
    scans = client.scans
    assert scorer.score_new() == 0 and client.scans == scans  # nothing new: no scan
    spec, adder = tiny_run().spec, StoreAdder(store)
    adder.add_first(np.zeros(spec.frame_shape, np.uint8))
    adder.add(np.zeros(spec.action_dim, np.float32), 1.0, 1.0, np.zeros(spec.frame_shape, np.uint8), False,
              policy_version=0)
    assert scorer.score_new() == 1 and client.scans == scans + 1
    assert not np.isnan(store.get(np.arange(store.num_inserted))["intrinsic"]).any()


def test_one_row_is_scored_on_one_thread_and_the_thread_count_comes_back():
    store, agent = filled_store(WARMUP + 17), nasa_agent()
    threads_seen = []
    score = agent.score

    def recording(obs, action, next_obs):  # noqa: ANN001, ANN202
        threads_seen.append((len(obs), torch.get_num_threads()))
        return score(obs, action, next_obs)

    agent.score = recording
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        scorer = IntrinsicScorer(agent, LocalReplay(store, np.random.default_rng(0)), WARMUP, batch_size=16)
        scorer.catch_up()  # the warm-up's zeros, then 16 rows, then the last one
        after = torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
    assert threads_seen == [(16, 2), (1, 1)]
    assert after == 2


class ThreadRecordingClient(LocalReplay):
    """Records which thread asks for the owed rows."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self.askers: set[str] = set()

    def unscored(self, after: int, limit: int):  # noqa: ANN201
        self.askers.add(threading.current_thread().name)
        return super().unscored(after, limit)


def add_steps(store: ReplayStore, n: int) -> None:
    spec, adder = tiny_run().spec, StoreAdder(store)
    rng = np.random.default_rng(store.num_inserted)
    adder.add_first(rng.integers(0, 255, spec.frame_shape, np.uint8))
    for _ in range(n):
        adder.add(rng.uniform(-1, 1, spec.action_dim).astype(np.float32), 1.0, 1.0,
                  rng.integers(0, 255, spec.frame_shape, np.uint8), False, policy_version=0)


def test_fetching_ahead_the_updates_thread_never_asks_and_every_row_is_scored_once_as_a_blocking_ask_would():
    store, agent = filled_store(30), nasa_agent()
    client = ThreadRecordingClient(store, np.random.default_rng(0))
    scorer = IntrinsicScorer(agent, client, WARMUP, batch_size=8)
    with scorer.fetching_ahead(idle_s=0.001):
        for _ in range(6):  # steps stored while updates run: each scored at a later update
            add_steps(store, 5)
            deadline = time.monotonic() + 10
            while scorer.scored < store.num_inserted - WARMUP and time.monotonic() < deadline:
                scorer.score_new()
                time.sleep(0.001)
    scorer.catch_up()
    assert threading.current_thread().name not in client.askers and client.askers == {"score-ahead"}
    assert scorer.scored == store.num_inserted - WARMUP  # no row twice
    stored = store.get(np.arange(store.num_inserted))["intrinsic"]
    assert np.all(stored[:WARMUP] == 0.0)
    rows = store.get(np.arange(WARMUP, store.num_inserted))
    expected = agent.score(torch.as_tensor(rows["obs"]), torch.as_tensor(rows["action"]),
                           torch.as_tensor(rows["next_obs"]))["intrinsic"].numpy()
    np.testing.assert_allclose(stored[WARMUP:], expected, rtol=1e-5, atol=1e-6)


def test_rows_fetched_ahead_but_not_scored_when_the_block_ends_are_scored_by_catch_up_once():
    store, agent = filled_store(WARMUP), nasa_agent()
    client = CountingClient(store, np.random.default_rng(0))
    scorer = IntrinsicScorer(agent, client, WARMUP, batch_size=4)
    with scorer.fetching_ahead(idle_s=0.001):
        add_steps(store, 10)
        deadline = time.monotonic() + 10
        while client.scans < 3 and time.monotonic() < deadline:  # 10 rows, 4 at a time: all fetched
            time.sleep(0.001)
        with pytest.raises(RuntimeError):
            scorer.catch_up()  # its thread may not have fetched everything yet
    assert scorer.scored == 0
    scans = client.scans
    scorer.catch_up()
    assert scorer.scored == 10 and not np.isnan(store.get(np.arange(store.num_inserted))["intrinsic"]).any()
    assert client.scans == scans  # what the thread fetched covers every row: no ask again


class FailingClient(LocalReplay):
    def unscored(self, after: int, limit: int):  # noqa: ANN201
        raise OSError("the replay's answer could not be read")


def test_a_failure_of_the_fetching_thread_is_raised_in_the_updates_thread():
    store, agent = filled_store(WARMUP + 3), nasa_agent()
    scorer = IntrinsicScorer(agent, FailingClient(store, np.random.default_rng(0)), WARMUP, batch_size=4)
    with scorer.fetching_ahead(idle_s=0.001):
        deadline = time.monotonic() + 10
        while scorer._fetch_error is None and time.monotonic() < deadline:
            time.sleep(0.001)
        with pytest.raises(RuntimeError, match="fetching owed rows") as caught:
            scorer.score_new()
    assert isinstance(caught.value.__cause__, OSError)
