"""The replay service's insert, sample and unscored paths, in process (no Zenoh session)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from services.replay.service import ReplayArgs, ReplayService, check_args
from shared import wire
from shared.config import ConfigError, default_config
from shared.envs import EnvSpec
from shared.replay.client import decode_reply
from shared.run_config import RunConfig
from shared.schedule import burst_extra, stored_updates, updates_due
from shared.service import StopFlag, parse

SHAPE = (3, 16, 16)
SPEC = EnvSpec(SHAPE, 3, 2)


def make_service(tmp_path, warmup=4, steps=100, session=None, stop=None, without_replacement=False,
                 no_rate_limit=False, max_abs_reward=wire.Bounds.max_abs_reward, warmup_burst=False,
                 updates_before_store=False):
    config = default_config("nasa_td3", "cpu-small")
    config.env.image_size, config.warmup_steps, config.steps = 16, warmup, steps
    config.warmup_burst, config.updates_before_store = warmup_burst, updates_before_store
    config.sample_without_replacement = without_replacement
    args = ReplayArgs(config=config, data=tmp_path, error_buffer=4, no_rate_limit=no_rate_limit,
                      max_abs_reward=max_abs_reward)
    run = RunConfig(config, SPEC)
    return ReplayService(args, session, StopFlag() if stop is None else stop, run)  # type: ignore[arg-type]


def batch(actor=0, inc=1, episode=0, start=0, n=3, last=False, seed=0, shape=SHAPE):
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n, *shape), dtype=np.uint8)
    first = rng.integers(0, 256, (1, *shape), dtype=np.uint8) if start == 0 else None
    lasts = np.zeros(n, np.uint8)
    lasts[-1] = last
    return wire.TransitionBatch(
        actor, inc, episode, start, n, list(shape), wire.encode_frames(frames),
        wire.encode_frames(first) if first is not None else None,
        rng.uniform(-1, 1, (n, 2)).astype("<f4").tobytes(), np.ones(n, "<f4").tobytes(),
        np.ones(n, "<f4").tobytes(), lasts.tobytes(), np.arange(n, dtype="<i8").tobytes(),
    ), frames, first


def test_inserts_are_stitched_by_episode_and_step(tmp_path):
    svc = make_service(tmp_path)
    msg, frames, first = batch(n=3)
    assert svc.insert_batch(msg) == 3
    assert svc.insert_batch(batch(start=3, n=2, seed=1)[0]) == 2
    # a gap, another episode, or a restarted actor's old episode are never stitched
    assert svc.insert_batch(batch(start=9, n=2)[0]) == 0
    assert svc.insert_batch(batch(episode=5, start=5, n=2)[0]) == 0
    assert svc.insert_batch(batch(inc=2, start=5, n=2)[0]) == 0
    assert svc.dropped == 6 and svc.store.num_inserted == 5
    # a new incarnation starting an episode is accepted; the replay rejects an older one
    assert svc.insert_batch(batch(inc=2, n=2, last=True)[0]) == 2
    with pytest.raises(ValueError, match="older"):
        svc.insert_batch(batch(inc=1, n=1)[0])
    with pytest.raises(wire.WireError, match="frame shape"):
        svc.insert_batch(batch(inc=3, shape=(3, 8, 8))[0])
    svc.store.close()


def test_every_row_is_stored_unscored_and_samples_follow_the_ratio(tmp_path):
    svc = make_service(tmp_path, warmup=4)
    req = wire.SampleRequest(8, wait_s=0.0)
    msg, frames, first = batch(n=5)
    msg4 = wire.TransitionBatch(**{**msg.__dict__, "n": 4, "frames": wire.encode_frames(frames[:4]),
                                   "actions": msg.actions[:32], "rewards": msg.rewards[:16],
                                   "discounts": msg.discounts[:16], "lasts": msg.lasts[:4],
                                   "policy_versions": msg.policy_versions[:32]})
    assert svc.insert_batch(msg4) == 4
    assert not svc.sample(req).ok  # the first sample needs warm-up + 1 inserts
    rest = wire.TransitionBatch(**{**msg.__dict__, "start": 4, "n": 1, "first_frame": None,
                                   "frames": wire.encode_frames(frames[4:]), "actions": msg.actions[32:],
                                   "rewards": msg.rewards[16:], "discounts": msg.discounts[16:],
                                   "lasts": msg.lasts[4:], "policy_versions": msg.policy_versions[32:]})
    assert svc.insert_batch(rest) == 1
    # warm-up rows too: the scorer, not the replay, gives them their zero
    assert np.isnan(svc.store._intrinsic[:5]).all()
    oks = [svc.sample(req).ok for _ in range(10)]
    assert sum(oks) == 4  # the error buffer of 4 samples, then inserts must come
    assert svc.insert_batch(batch(start=5, n=2, seed=2)[0]) == 2
    reply = svc.sample(req)
    assert reply.ok and reply.window_shape == [8, 12, 16, 16]
    b = decode_reply(reply, SPEC)
    for i, g in enumerate(b["index"].tolist()):
        if g < 5:  # newest frame of the window is the transition's next frame
            np.testing.assert_array_equal(b["next_obs"][i, 6:], frames[g])
            assert b["policy_version"][i] == g
    svc.store.close()


def test_a_restarted_replay_restores_its_rate_limiter_from_the_store(tmp_path):
    svc = make_service(tmp_path, warmup=4)
    assert svc.insert_batch(batch(n=9, last=True)[0]) == 9
    svc.store.close()
    again = make_service(tmp_path, warmup=4)
    # G samples per insert past warm-up count as done: inserts 9, samples G * (9 - 4)
    g = again.config.updates_per_step
    assert again.limiter.stats()["inserts"] == 9 and again.limiter.stats()["samples"] == g * 5
    again.store.close()


def test_the_rate_limit_lets_the_learner_make_the_warm_up_burst_at_once_then_keeps_g_a_step(tmp_path):
    """With --warmup-burst the learner may make the burst's updates as soon as the step after the
    warm-up is stored, without more inserts, and the actors wait for it meanwhile; then the limiter
    holds G a step as without it. Restarted, the replay counts the burst as made."""
    warmup, req = 6, wire.SampleRequest(2, wait_s=0.0)
    served, inserts_wait = {}, {}
    for burst in (False, True):
        svc = make_service(tmp_path / str(burst), warmup=warmup, warmup_burst=burst)
        assert svc.insert_batch(batch(n=warmup + 1)[0]) == warmup + 1
        inserts_wait[burst] = not svc.limiter.can_insert()
        served[burst] = sum(svc.sample(req).ok for _ in range(3 * warmup))
        assert svc.limiter.can_insert()  # the learner has drawn what it may: the actors go on
        svc.store.close()
    assert served[True] - served[False] == burst_extra(svc.config) > 0
    assert inserts_wait == {False: False, True: True}
    again = make_service(tmp_path / "True", warmup=warmup, warmup_burst=True)
    assert again.limiter.samples == updates_due(warmup + 1, again.config) == warmup  # G = 1: the burst
    again.store.close()


def drawn_by_stored(svc: ReplayService, first: int, last: int) -> dict[int, int]:
    """The samples a learner drawing all it may has drawn, by the transitions stored: `first` of them
    at once, then one at a time up to `last`."""
    req, drawn = wire.SampleRequest(2, wait_s=0.0), {}
    assert svc.insert_batch(batch(n=first)[0]) == first
    for stored in range(first, last + 1):
        if stored > first:
            assert svc.insert_batch(batch(start=stored - 1, n=1, seed=stored)[0]) == 1
        while svc.sample(req).ok:
            pass
        drawn[stored] = svc.limiter.samples
    svc.store.close()
    return drawn


def test_with_updates_before_store_the_learner_samples_a_replay_one_insert_smaller(tmp_path):
    """SAC-AE's order (--algo sac_ae): a step's updates come before its transition is stored, so the
    limiter allows on n stored transitions the samples it allows on n + 1 without, the burst on the
    warm-up's own; restarted, the replay counts them as made."""
    warmup, last = 6, 10
    drawn = {before: drawn_by_stored(make_service(tmp_path / str(before), warmup=warmup, warmup_burst=True,
                                                  updates_before_store=before), warmup - 1, last)
             for before in (False, True)}
    sooner = range(warmup - 1, last)
    assert [drawn[True][n] for n in sooner] == [drawn[False][n + 1] for n in sooner]
    assert drawn[True][warmup - 1] == 0 < drawn[True][warmup]  # the burst, on the warm-up's rows
    again = make_service(tmp_path / "True", warmup=warmup, warmup_burst=True, updates_before_store=True)
    assert again.limiter.samples == stored_updates(last, again.config) == updates_due(last + 1, again.config)
    again.store.close()


def test_with_updates_before_store_and_no_warm_up_the_second_step_samples_the_first_row(tmp_path):
    """A warm-up of 0 with its burst: the first step makes no updates and the second its G before
    its transition is stored, on the one row stored; the limiter allows that, one insert sooner than
    without the flag, though its minimum size stays one row."""
    last = 6
    drawn = {before: drawn_by_stored(make_service(tmp_path / str(before), warmup=0, warmup_burst=True,
                                                  updates_before_store=before), 1, last)
             for before in (False, True)}
    assert [drawn[True][n] for n in range(1, last)] == [drawn[False][n + 1] for n in range(1, last)]


def test_unscored_requests_return_the_oldest_unscored_rows_outside_the_ratio(tmp_path):
    svc = make_service(tmp_path, warmup=4)
    msg, frames, first = batch(n=7, last=True)
    assert svc.insert_batch(msg) == 7
    samples = svc.limiter.samples
    reply = svc.unscored(wire.UnscoredRequest(after=0, limit=2))
    assert reply.ok and reply.batch_size == 2 and reply.num_inserted == 7
    b = decode_reply(reply, SPEC)
    np.testing.assert_array_equal(b["index"], [0, 1])
    np.testing.assert_array_equal(b["next_obs"][1, 6:], frames[1])  # row 1's newest frame
    assert np.isnan(b["intrinsic"]).all()
    svc.store.set_intrinsic(np.arange(6), np.full(6, 0.5))
    reply = svc.unscored(wire.UnscoredRequest(after=0, limit=8))
    np.testing.assert_array_equal(decode_reply(reply, SPEC)["index"], [6])
    svc.store.set_intrinsic(np.array([6]), np.array([0.5]))
    reply = svc.unscored(wire.UnscoredRequest(after=5, limit=8))
    assert not reply.ok and reply.reason == "none unscored" and reply.num_inserted == 7
    assert svc.limiter.samples == samples  # scoring requests are not training samples
    with pytest.raises(wire.WireError, match="limit 0"):
        svc.unscored(wire.UnscoredRequest(after=0, limit=0))
    svc.store.close()


def test_sampling_without_replacement_waits_for_a_full_batch_and_never_repeats(tmp_path):
    svc = make_service(tmp_path, warmup=4, without_replacement=True, no_rate_limit=True)
    assert svc.insert_batch(batch(n=7)[0]) == 7
    reply = svc.sample(wire.SampleRequest(8, wait_s=0.0))
    assert not reply.ok and "fewer than 8" in reply.reason  # not ready yet: no smaller batch
    assert svc.insert_batch(batch(start=7, n=3, seed=1, last=True)[0]) == 3
    for _ in range(20):
        index = decode_reply(svc.sample(wire.SampleRequest(8, wait_s=0.0)), SPEC)["index"]
        assert len(set(index.tolist())) == 8
    svc.store.close()


def test_transitions_past_the_step_budget_are_dropped_without_calling_them_orphans(tmp_path, capsys):
    svc = make_service(tmp_path, steps=5)
    assert svc.insert_batch(batch(n=3)[0]) == 3
    assert svc.insert_batch(batch(start=3, n=3, seed=1)[0]) == 2  # the budget cuts this one
    assert svc.insert_batch(batch(start=6, n=2, seed=2)[0]) == 0  # and every one after it
    assert svc.dropped == 3 and svc.store.num_inserted == 5
    out, err = capsys.readouterr()
    assert "dropped" not in out + err
    svc.store.close()


@pytest.mark.parametrize("flag, value, says", [
    ("--max-abs-reward", "nan", "max-abs-reward"), ("--max-abs-reward", "1e6", "at most 1000"),
    ("--max-abs-reward", "-1", "max-abs-reward"), ("--stats-every-s", "0", "stats-every-s"),
    ("--snapshot-every", "0", "snapshot-every"), ("--sample-threads", "0", "sample-threads"),
    ("--error-buffer", "inf", "error-buffer"), ("--camera-id", "7", "camera"),
])
def test_a_flag_it_cannot_serve_with_is_refused_before_it_connects(tmp_path, flag, value, says):
    # No router listens here: the flag must be the error, with exit 2 and nothing opened.
    done = subprocess.run([sys.executable, "-m", "services.replay", "--data", str(tmp_path / "run"),
                           "--connect", "tcp/127.0.0.1:9", flag, value],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and says in done.stderr, done.stderr
    assert not (tmp_path / "run").exists()


def test_a_flag_the_parser_refuses_is_one_line_and_exit_2_so_nasa_up_shows_it(tmp_path):
    # `nasa up` names a service that refused its input by its log's last line: the reason, not a border.
    done = subprocess.run([sys.executable, "-m", "services.replay", "--data", str(tmp_path / "run"),
                           "--connect", "tcp/127.0.0.1:9", "--snapshot-evry", "5"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr == ("python -m services.replay: error: Unrecognized options: --snapshot-evry, 5; "
                           "did you mean --snapshot-every? (`python -m services.replay --help` lists its "
                           "flags)\n")
    assert not (tmp_path / "run").exists()


def test_the_camera_is_checked_unless_nasa_up_has_checked_it(tmp_path):
    argv = ["--data", str(tmp_path), "--task", "cartpole-balance", "--camera-id", "99"]
    with pytest.raises(ConfigError, match="env.camera_id 99 is not a camera of cartpole-balance"):
        check_args(parse(ReplayArgs, argv, "replay")[0])  # started alone: its own check
    check_args(parse(ReplayArgs, [*argv, "--camera-checked"], "replay")[0])  # no model loaded again


def test_a_refused_batch_is_acknowledged_so_its_actor_does_not_wait_on_it(tmp_path):
    class Puts:  # the service's session, as far as acknowledgements go
        def __init__(self) -> None:
            self.acks: list[wire.InsertAck] = []

        def put(self, key, payload, **kw) -> None:  # noqa: ANN001, ANN003
            self.acks.append(wire.decode(payload, wire.InsertAck))

    session, stop = Puts(), StopFlag()
    svc = make_service(tmp_path, session=session, stop=stop, no_rate_limit=True)
    svc.insert_batch(batch(inc=5, n=3)[0])
    svc._inserts.put(batch(inc=4, n=3, seed=1)[0])  # an older incarnation: the store refuses it
    svc._inserts.put(batch(inc=5, episode=1, n=2, seed=2)[0])
    loop = threading.Thread(target=svc._insert_loop)
    loop.start()
    deadline = time.monotonic() + 30
    while len(session.acks) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set("test done")
    loop.join(5)
    assert [(a.incarnation, a.num_inserted) for a in session.acks] == [(4, 3), (5, 5)]
    assert svc.invalid == 1
    # The ack says the older incarnation's batch was refused, and for good; the newer one's was stored.
    stale, stored = session.acks
    assert "older than incarnation 5" in stale.refused and stale.lasting
    assert stored.refused == "" and not stored.lasting


def test_a_batch_that_continues_no_episode_is_acknowledged_as_refused_but_not_for_good(tmp_path):
    svc = make_service(tmp_path, no_rate_limit=True)
    assert svc._take(batch(inc=5, start=3, n=2)[0]) == (
        "not the continuation of an episode begun here", False)
    assert svc._take(batch(inc=5, n=2, seed=1)[0]) == ("", False)
    assert svc.store.num_inserted == 2


def test_restarts_in_the_middle_of_episodes_leave_one_entry_per_actor_id(tmp_path):
    # `nasa up` restarts a dead actor under its id with a new incarnation: a week of restarts must
    # not leave an entry behind for each incarnation that died mid-episode.
    svc = make_service(tmp_path, steps=10_000, no_rate_limit=True)
    for inc in range(1, 201):
        assert svc.insert_batch(batch(actor=7, inc=inc, n=2, seed=inc)[0]) == 2
    assert len(svc._episodes) == 1
    # The incarnation before the newest (a zombie) continuing its episode is dropped, not stored
    # into the episode the newer one's start closed.
    assert svc.insert_batch(batch(actor=7, inc=199, start=2, n=2)[0]) == 0
    assert svc.insert_batch(batch(actor=7, inc=200, start=2, n=2, last=True)[0]) == 2
    assert svc._episodes == {}
    svc.store.close()


def test_an_episode_the_store_closed_for_want_of_steps_is_dropped_not_refused_as_invalid(tmp_path):
    svc = make_service(tmp_path, steps=10_000, no_rate_limit=True)
    svc.store.close()
    from shared.replay import ReplayStore

    svc.store = ReplayStore(8, SHAPE, 3, 2)  # a small replay: one capacity of inserts passes quickly
    assert svc.insert_batch(batch(actor=3, n=2)[0]) == 2  # its actor stalls mid-episode
    for episode in range(3):  # while another fills the whole replay
        assert svc.insert_batch(batch(actor=4, episode=episode, n=4, seed=episode, last=True)[0]) == 4
    assert not svc.store.is_open(0)
    assert svc._take(batch(actor=3, start=2, n=2, seed=9)[0]) == (
        "not the continuation of an episode begun here", False)
    assert svc.invalid == 0 and 3 not in svc._episodes
    assert svc.insert_batch(batch(actor=3, episode=1, n=2, seed=10)[0]) == 2  # its next episode is stored


def test_actor_ids_gone_for_good_are_forgotten_once_the_store_closes_their_episodes(tmp_path, monkeypatch):
    # Replicas of a scaled actor service take a new random id at each start: a week of restarts
    # must not leave an entry for each id that died mid-episode.
    from services.replay import service
    from shared.replay import ReplayStore

    monkeypatch.setattr(service, "FORGET_EVERY", 32, raising=False)  # a small run shows the bound
    svc = make_service(tmp_path, steps=10**6, no_rate_limit=True)
    svc.store.close()
    svc.store = ReplayStore(64, SHAPE, 3, 2)
    for k in range(300):
        assert svc.insert_batch(batch(actor=10_000 + k, n=2, seed=k)[0]) == 2  # then gone
        assert svc.insert_batch(batch(actor=1, inc=k, n=2, seed=k, last=True)[0]) == 2  # the fleet goes on
    assert len(svc._episodes) <= 2 * 32
