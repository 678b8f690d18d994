"""ReplayStore against a naive buffer that keeps a full stack per transition."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np
import pytest

from shared.replay import ReplayStore

SHAPE = (3, 16, 16)
K = 3
A = 2


class NaiveStack:
    """What shared.envs.FrameStack produces: the reset frame repeated k times, then a sliding window."""

    def __init__(self, first: np.ndarray, k: int = K) -> None:
        self.frames = deque([first] * k, maxlen=k)

    def push(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        obs = np.concatenate(self.frames, axis=0)
        self.frames.append(frame)
        return obs, np.concatenate(self.frames, axis=0)


def random_frame(rng: np.random.Generator, prev: np.ndarray | None = None) -> np.ndarray:
    # Mostly small changes (like real video) with occasional big ones, to exercise wrapping deltas.
    if prev is None or rng.random() < 0.1:
        return rng.integers(0, 256, SHAPE, dtype=np.uint8)
    f = prev.copy()
    f[:, rng.integers(0, 16), :] = rng.integers(0, 256, (3, 16), dtype=np.uint8)
    return f


def fill(store: ReplayStore, rng: np.random.Generator, n_steps: int, actors: int = 3,
         max_len: int = 40, die_prob: float = 0.02, first_actor: int = 0) -> dict[int, dict]:
    """Interleave several actors with random episode lengths; returns naive records by index."""
    naive: dict[int, dict] = {}
    state: dict[int, tuple[int, NaiveStack, np.ndarray, int]] = {}
    incarnation = dict.fromkeys(range(first_actor, first_actor + actors), 0)
    done = 0
    steps: dict[int, int] = {}
    while done < n_steps:
        a = first_actor + int(rng.integers(actors))
        if a not in state:
            f0 = random_frame(rng)
            ep = store.begin_episode(f0, actor_id=a, incarnation=incarnation[a])
            state[a] = (ep, NaiveStack(f0), f0, int(rng.integers(1, max_len)))
            continue
        ep, stack, prev, remaining = state[a]
        if rng.random() < die_prob:  # the actor dies mid-episode and restarts
            incarnation[a] += 1
            del state[a]
            continue
        frame = random_frame(rng, prev)
        obs, nxt = stack.push(frame)
        action = rng.uniform(-1, 1, A).astype(np.float32)
        reward = float(rng.normal())
        last = remaining == 1
        g = store.add(ep, action, reward, 0.99, frame, last, policy_version=done)
        step = steps.get(ep, 0)
        steps[ep] = step + 1
        naive[g] = dict(obs=obs, next_obs=nxt, action=action, reward=np.float32(reward),
                        episode_id=ep, actor_id=a, incarnation=incarnation[a], step=step,
                        policy_version=done)
        done += 1
        if last:
            del state[a]
        else:
            state[a] = (ep, stack, frame, remaining - 1)
    return naive


def check_batch(batch: dict, naive: dict[int, dict]) -> None:
    for i, g in enumerate(batch["index"].tolist()):
        r = naive[g]
        np.testing.assert_array_equal(batch["obs"][i], r["obs"], err_msg=f"obs of {g}")
        np.testing.assert_array_equal(batch["next_obs"][i], r["next_obs"], err_msg=f"next of {g}")
        window = np.concatenate([r["obs"], r["next_obs"][-SHAPE[0] :]])
        np.testing.assert_array_equal(batch["window"][i], window, err_msg=f"window of {g}")
        np.testing.assert_array_equal(batch["action"][i], r["action"])
        assert batch["reward"][i] == r["reward"]
        for key in ("episode_id", "actor_id", "incarnation", "step", "policy_version"):
            assert batch[key][i] == r[key], (key, g)


@pytest.mark.parametrize(
    "capacity,chunk_len,compression",
    [(10_000, 8, "lz4"), (10_000, 8, "zstd"), (150, 8, "lz4"), (97, 3, "zstd"), (64, 16, "lz4")],
)
def test_stacks_match_naive_buffer(capacity: int, chunk_len: int, compression: str) -> None:
    rng = np.random.default_rng(capacity)
    store = ReplayStore(capacity, SHAPE, K, A, chunk_len=chunk_len, compression=compression)
    naive = fill(store, rng, 600)
    assert store.num_inserted == 600
    assert len(store) == min(600, capacity)
    batch = store.sample(256, np.random.default_rng(1))
    assert batch["obs"].shape == (256, 3 * K, 16, 16) and batch["obs"].dtype == np.uint8
    assert batch["next_obs"].shape == (256, 3 * K, 16, 16)
    assert batch["action"].shape == (256, A) and batch["action"].dtype == np.float32
    # Uniform over the live window only: nothing evicted is ever returned.
    assert batch["index"].min() >= 600 - min(600, capacity)
    check_batch(batch, naive)
    # Every live transition, not only a sample, rebuilds exactly (wrap-around included).
    for g in range(600 - len(store), 600, 50):
        sub = store.sample(1, np.random.default_rng(g))
        check_batch(sub, naive)
    store.close()


def test_every_live_transition_exact_after_wraparound() -> None:
    rng = np.random.default_rng(7)
    store = ReplayStore(50, SHAPE, K, A, chunk_len=4)
    naive = fill(store, rng, 333, actors=2, max_len=12)
    seen = set()
    for s in range(40):
        b = store.sample(64, np.random.default_rng(s))
        check_batch(b, naive)
        seen.update(b["index"].tolist())
    assert seen == set(range(283, 333))  # all 50 live, none evicted
    # Chunks no live transition needs were freed: memory follows the window, not history.
    assert store.stats()["frames"] < 50 * 2 + 2 * 4 * 2


def test_sample_is_deterministic_and_uniform() -> None:
    store = ReplayStore(1000, SHAPE, K, A)
    fill(store, np.random.default_rng(0), 1200)
    a = store.sample(32, np.random.default_rng(5))
    b = store.sample(32, np.random.default_rng(5))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    idx = np.concatenate([store.sample(256, np.random.default_rng(s))["index"] for s in range(40)])
    counts = np.bincount(idx - 200, minlength=1000)
    assert idx.min() >= 200 and idx.max() < 1200
    # ~10 hits per item; a chi-square far above its 999 dof would mean a biased sampler.
    chi2 = ((counts - counts.mean()) ** 2 / counts.mean()).sum()
    assert chi2 < 1200


def test_per_chunk_sampling_is_exact_and_uniform_marginally() -> None:
    store = ReplayStore(300, SHAPE, K, A, chunk_len=8)
    naive = fill(store, np.random.default_rng(3), 500)
    idx = []
    for s in range(300):
        b = store.sample(64, np.random.default_rng(s), per_chunk=4)
        check_batch(b, naive) if s < 5 else None
        idx.append(b["index"])
    idx = np.concatenate(idx)
    assert idx.min() >= 200
    counts = np.bincount(idx - 200, minlength=300)
    # 64 hits expected per item; per-chunk grouping must not bias the marginal.
    assert counts.min() > 25 and counts.max() < 115, (counts.min(), counts.max())
    # Early-chunk and late-chunk transitions are hit equally often on average.
    steps = store._step[np.arange(200, 500) % 300]
    assert abs(counts[steps % 8 == 0].mean() - counts.mean()) < 8


def test_intrinsic_slot_and_truncate() -> None:
    store = ReplayStore(100, SHAPE, K, A)
    naive = fill(store, np.random.default_rng(4), 80)
    b = store.sample(16, np.random.default_rng(0))
    assert np.isnan(b["intrinsic"]).all()
    store.set_intrinsic(np.array([3, 5, 79]), np.array([0.5, 1.5, 2.5]))
    store.set_intrinsic(np.array([0]), np.array([9.0]))
    found = {}
    for s in range(50):
        b = store.sample(64, np.random.default_rng(s))
        found.update(zip(b["index"].tolist(), b["intrinsic"].tolist(), strict=True))
    assert found[3] == 0.5 and found[5] == 1.5 and found[79] == 2.5 and found[0] == 9.0
    store.truncate(60)
    assert store.num_inserted == 60 and len(store) == 60
    for s in range(10):
        b = store.sample(64, np.random.default_rng(s))
        assert b["index"].max() < 60
        check_batch(b, naive)
    # Adding continues at index 60 in a new episode; stacks of old episodes untouched.
    f0 = np.zeros(SHAPE, np.uint8)
    ep = store.begin_episode(f0, actor_id=0, incarnation=5)
    assert store.add(ep, np.zeros(A), 0.0, 1.0, f0 + 1, False) == 60


def test_unscored_rows_oldest_first_and_get_by_index() -> None:
    store = ReplayStore(50, SHAPE, K, A)  # 80 inserted, 30 evicted
    naive = fill(store, np.random.default_rng(5), 80)
    store.set_intrinsic(np.array([40, 41, 60]), np.array([0.1, 0.2, 0.3]))
    np.testing.assert_array_equal(store.unscored(0, 5), [30, 31, 32, 33, 34])  # evicted ones skipped
    np.testing.assert_array_equal(store.unscored(39, 4), [39, 42, 43, 44])  # scored ones skipped
    np.testing.assert_array_equal(store.unscored(59, 100), [59, *range(61, 80)])
    assert len(store.unscored(80, 10)) == 0 and len(store.unscored(0, 0)) == 0
    b = store.get(store.unscored(55, 7))
    np.testing.assert_array_equal(b["index"], [55, 56, 57, 58, 59, 61, 62])
    check_batch(b, naive)
    assert np.isnan(b["intrinsic"]).all()
    for bad in (np.array([29]), np.array([80]), np.array([], np.int64), np.zeros((2, 2), np.int64)):
        with pytest.raises(ValueError, match="index"):
            store.get(bad)
    both = store.get_unscored(55, 7)
    np.testing.assert_array_equal(both["index"], b["index"])
    np.testing.assert_array_equal(both["obs"], b["obs"])
    assert store.get_unscored(80, 10) is None


def test_unscored_rows_are_read_before_an_insert_evicts_them() -> None:
    store = ReplayStore(200, SHAPE, K, A)
    f = np.zeros(SHAPE, np.uint8)
    ep = store.begin_episode(f)
    for _ in range(250):  # full: every insert evicts the oldest row, the first a scorer asks for
        store.add(ep, np.zeros(A), 0.0, 0.99, f, False)
    stop = threading.Event()

    def insert() -> None:
        while not stop.is_set():
            store.add(ep, np.zeros(A), 0.0, 0.99, f, False)

    inserter = threading.Thread(target=insert)
    inserter.start()
    try:
        for _ in range(2000):
            batch = store.get_unscored(0, 64)
            assert batch is not None and len(batch["index"]) == 64
    finally:
        stop.set()
        inserter.join()


def test_dead_actor_episode_is_closed() -> None:
    store = ReplayStore(100, SHAPE, K, A)
    f = [np.full(SHAPE, i, np.uint8) for i in range(10)]
    ep1 = store.begin_episode(f[0], actor_id=1, incarnation=0)
    store.add(ep1, np.zeros(A), 0.0, 1.0, f[1], False)
    # Actor 1 restarts (new incarnation) and begins again: ep1 is closed, not continued.
    ep2 = store.begin_episode(f[5], actor_id=1, incarnation=1)
    assert ep2 != ep1
    with pytest.raises(ValueError, match="closed"):
        store.add(ep1, np.zeros(A), 0.0, 1.0, f[2], False)
    store.add(ep2, np.zeros(A), 0.0, 1.0, f[6], False)
    with pytest.raises(ValueError, match="older than incarnation"):
        store.begin_episode(f[0], actor_id=1, incarnation=0)
    b = store.sample(32, np.random.default_rng(0))
    for i in range(32):
        frames = set(np.unique(b["next_obs"][i]).tolist()) | set(np.unique(b["obs"][i]).tolist())
        # A stack holds frames of one episode only: {0,1} for ep1, {5,6} for ep2.
        assert frames <= {0, 1} or frames <= {5, 6}, frames
    assert store.stats()["open_episodes"] == 1


def test_bad_input_rejected_and_nothing_lost() -> None:
    store = ReplayStore(100, SHAPE, K, A)
    naive = fill(store, np.random.default_rng(9), 30, actors=1, max_len=1000)
    ep = max(r["episode_id"] for r in naive.values())
    ok = np.zeros(SHAPE, np.uint8)
    before = store.stats()
    bad_calls = [
        (dict(next_frame=np.zeros((3, 16, 15), np.uint8)), "shape"),
        (dict(next_frame=np.zeros(SHAPE, np.float32)), "uint8"),
        (dict(reward=float("nan")), "reward must be finite"),
        (dict(reward=float("inf")), "reward must be finite"),
        (dict(episode_id=12345), "unknown"),
        (dict(action=np.array([0.0, 1.5])), "outside"),
        (dict(action=np.array([0.0, np.nan])), "non-finite"),
        (dict(action=np.zeros(3)), "shape"),
        (dict(discount=1.5), "discount"),
        (dict(intrinsic=float("inf")), "intrinsic"),
        (dict(policy_version=-1), "policy_version"),
        (dict(reward=1e39), "reward must be finite in float32"),  # finite, but not as stored
        (dict(intrinsic=-1e39), "intrinsic"),
        (dict(policy_version=2**63), "policy_version"),
    ]
    for override, msg in bad_calls:
        kw = dict(episode_id=ep, action=np.zeros(A), reward=0.0, discount=1.0, next_frame=ok,
                  last=False)
        kw.update(override)
        with pytest.raises(ValueError, match=msg):
            store.add(**kw)
    with pytest.raises(ValueError, match="shape"):
        store.begin_episode(np.zeros((16, 16, 3), np.uint8))
    after = store.stats()
    for key in ("size", "num_inserted", "frames", "frame_bytes", "episodes"):
        assert after[key] == before[key], key
    for s in range(5):
        check_batch(store.sample(64, np.random.default_rng(s)), naive)
    # The open episode continues normally after the rejected calls.
    g = store.add(ep, np.zeros(A), 0.0, 1.0, ok, True)
    assert g == 30


def test_sampling_without_replacement_has_no_repeat_and_stays_uniform() -> None:
    store = ReplayStore(200, SHAPE, K, A)
    naive = fill(store, np.random.default_rng(2), 300)  # 200 live: [100, 300)
    idx = []
    for s in range(200):
        b = store.sample(128, np.random.default_rng(s), replace=False)
        assert len(np.unique(b["index"])) == 128  # no transition twice in a batch
        check_batch(b, naive) if s < 3 else None
        idx.append(b["index"])
    idx = np.concatenate(idx)
    assert idx.min() >= 100 and idx.max() < 300
    counts = np.bincount(idx - 100, minlength=200)  # 128 hits expected per item
    chi2 = ((counts - counts.mean()) ** 2 / counts.mean()).sum()
    assert chi2 < 300  # 199 dof: a biased draw would be far above
    # with replacement, a batch of 128 from 200 repeats rows (what replace=False avoids)
    assert len(np.unique(store.sample(128, np.random.default_rng(0))["index"])) < 128
    whole = store.sample(200, np.random.default_rng(1), replace=False)
    assert sorted(whole["index"].tolist()) == list(range(100, 300))
    with pytest.raises(ValueError, match="201 distinct transitions from 200"):
        store.sample(201, np.random.default_rng(0), replace=False)
    with pytest.raises(ValueError, match="per_chunk"):
        store.sample(64, np.random.default_rng(0), per_chunk=4, replace=False)


def test_concurrent_writer_and_sampler() -> None:
    import threading

    # The same fills on a store of its own give every record the sampler may draw, before it runs.
    reference = ReplayStore(500, SHAPE, K, A)
    expected = fill(reference, np.random.default_rng(0), 100)
    expected |= fill(reference, np.random.default_rng(1), 1500, first_actor=10)
    store = ReplayStore(500, SHAPE, K, A)
    naive = fill(store, np.random.default_rng(0), 100)
    errors = []

    def sampler() -> None:
        try:
            for s in range(60):
                b = store.sample(32, np.random.default_rng(s))
                assert b["obs"].shape[0] == 32
                check_batch(b, expected)  # what a batch drawn while rows are evicted holds
        except Exception as e:  # surfaced below
            errors.append(e)

    t = threading.Thread(target=sampler)
    t.start()
    more = fill(store, np.random.default_rng(1), 1500, first_actor=10)
    t.join()
    assert not errors, errors
    naive.update(more)
    check_batch(store.sample(128, np.random.default_rng(0)), naive)


def test_real_rendered_frames() -> None:
    from shared.envs import make

    env = make("cartpole-balance", 0, render_quality="fast")
    rng = np.random.default_rng(0)
    store = ReplayStore(1000, (3, 84, 84), 3, env.action_dim, chunk_len=8)
    ts = env.reset()
    ep = store.begin_episode(ts.frame)
    stacks = {}
    for _ in range(60):
        obs = ts.obs
        a = rng.uniform(-1, 1, env.action_dim)
        ts = env.step(a)
        g = store.add(ep, a, ts.reward, ts.discount, ts.frame, ts.last)
        stacks[g] = (obs, ts.obs)
    b = store.sample(128, np.random.default_rng(0))
    for i, g in enumerate(b["index"].tolist()):
        np.testing.assert_array_equal(b["obs"][i], stacks[g][0])
        np.testing.assert_array_equal(b["next_obs"][i], stacks[g][1])
    st = store.stats()
    assert st["frame_bytes"] / st["frames"] < 21168 / 3  # compression is doing something


def test_episodes_left_open_by_actors_gone_for_good_leave_with_their_transitions(tmp_path) -> None:
    # Replicas of a scaled actor service take a new random id at each start: one that dies mid-episode
    # never continues its episode, and the store must not keep its last chunks for the rest of the run.
    capacity, chunk_len = 60, 8
    f = [np.full(SHAPE, i, np.uint8) for i in range(8)]
    with ReplayStore(capacity, SHAPE, K, A, data_dir=tmp_path, chunk_len=chunk_len) as store:
        for gone in range(100, 150):  # each a replica that added a few steps and died
            ep = store.begin_episode(f[0], actor_id=gone, incarnation=0)
            for t in range(3):
                store.add(ep, np.zeros(A), 0.0, 1.0, f[t + 1], False)
            live = store.begin_episode(f[4], actor_id=1, incarnation=gone)  # the fleet goes on
            for t in range(capacity):
                store.add(live, np.zeros(A), 0.0, 1.0, f[5 + t % 3], t == capacity - 1)
        stats = store.stats()
        # Only what the live transitions need: nothing of the 50 gone actors' episodes.
        assert stats["open_episodes"] == 0
        assert stats["episodes"] <= 2 and stats["chunks"] <= 2 * (capacity // chunk_len + 2)
        before = store.sample(16, np.random.default_rng(0))
    with ReplayStore(capacity, SHAPE, K, A, data_dir=tmp_path, chunk_len=chunk_len) as store:
        for key in ("episodes", "open_episodes", "chunks", "frames", "size"):
            assert store.stats()[key] == stats[key], key
        after = store.sample(16, np.random.default_rng(0))
    np.testing.assert_array_equal(after["obs"], before["obs"])


def test_an_open_episode_is_not_closed_by_its_own_inserts_in_a_small_replay() -> None:
    store = ReplayStore(4, SHAPE, K, A)
    ep = store.begin_episode(np.zeros(SHAPE, np.uint8), actor_id=0)
    for t in range(20):  # each add evicts the episode's own newest-but-one transition
        store.add(ep, np.zeros(A), 0.0, 1.0, np.full(SHAPE, t, np.uint8), False)
    assert store.stats()["open_episodes"] == 1 and len(store) == 4
