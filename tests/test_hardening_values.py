"""Issue 14, values: well-formed messages with bad values are refused on decode (shared.wire's value
checks), and no receiver's callback or thread dies of one. In process, no Zenoh."""

from __future__ import annotations

import math
import queue
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import zenoh

from services.learner.learner import Learner
from services.learner.status import StatusBoard
from shared import wire
from shared.service import Log
from shared.weights import WeightsSubscriber
from tests.test_replay_service import SPEC, batch, make_service
from tests.test_weights import _agent, _message

BOUNDS = wire.Bounds.of(SPEC)


def _with(msg: wire.Message, **fields: object) -> bytes:
    """msg encoded with some fields replaced by raw values (any type msgpack carries)."""
    body = msgpack.unpackb(wire.encode(msg), raw=False)
    return msgpack.packb({**body, **fields}, use_bin_type=True)


def _f4(*values: float) -> bytes:
    return np.asarray(values, "<f4").tobytes()


def _sample(payload: bytes) -> SimpleNamespace:
    """What a Zenoh subscriber callback receives, as far as the services read it."""
    return SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload))


@pytest.mark.parametrize("field, value, match", [
    ("rewards", _f4(3e38, 1, 1), "rewards"),  # finite but huge: the critic's loss overflows
    ("rewards", _f4(math.nan, 1, 1), "rewards"),
    ("discounts", _f4(1.5, 1, 1), "discounts"),
    ("discounts", _f4(-0.1, 1, 1), "discounts"),
    ("actions", np.full((3, 2), 1.5, "<f4").tobytes(), "actions"),
    ("actions", np.full((3, 2), math.inf, "<f4").tobytes(), "actions"),
    ("actions", _f4(0, 0, 0), "bytes"),  # the wrong action size for this run
    ("lasts", b"\x00\x07\x00", "lasts"),
    ("policy_versions", np.array([0, -1, 0], "<i8").tobytes(), "policy versions"),
    ("n", 2**64 - 1, "outside"),
    ("actor_id", -1, "outside"),
    ("frame_shape", [3, 8, 8], "frame shape"),
    ("frame_shape", ["3", 16, 16], "shape"),
    ("first_frame", None, "first_frame"),
])
def test_transition_values_are_checked_against_the_run(field, value, match):
    msg, _, _ = batch(n=3)
    decoded = wire.decode(wire.encode(msg), wire.TransitionBatch, BOUNDS)
    assert decoded.arrays["frames"].shape == (3, *SPEC.frame_shape)
    with pytest.raises(wire.WireError, match=match):
        wire.decode(_with(msg, **{field: value}), wire.TransitionBatch, BOUNDS)


def test_the_reward_bound_is_configurable():
    msg, _, _ = batch(n=3)
    payload = _with(msg, rewards=_f4(5e3, 1, 1))
    with pytest.raises(wire.WireError, match="rewards"):
        wire.decode(payload, wire.TransitionBatch, BOUNDS)
    assert wire.decode(payload, wire.TransitionBatch, wire.Bounds.of(SPEC, max_abs_reward=1e4))


@pytest.mark.parametrize("cls, msg, fields, match", [
    (wire.SampleRequest, wire.SampleRequest(8), {"wait_s": math.nan}, "wait_s"),
    (wire.SampleRequest, wire.SampleRequest(8), {"wait_s": -1.0}, "wait_s"),
    (wire.SampleRequest, wire.SampleRequest(8), {"batch_size": 2**63}, "batch_size"),
    (wire.UnscoredRequest, wire.UnscoredRequest(0, 8), {"after": 2**64 - 1}, "after"),
    (wire.UnscoredRequest, wire.UnscoredRequest(0, 8), {"limit": 10**9}, "limit"),
    (wire.SetIntrinsic, wire.SetIntrinsic(np.int64(1).tobytes(), _f4(0.5)),
     {"value": _f4(math.inf)}, "scores"),
    (wire.SetIntrinsic, wire.SetIntrinsic(np.int64(1).tobytes(), _f4(0.5)),
     {"index": np.int64(-5).tobytes()}, "indices"),
    (wire.ActorStatus, wire.ActorStatus(1, 2, 3, 4, 5, 1.0, [[1.0, 10]]), {"episode_returns": [["x", 10]]},
     "episode return"),
    (wire.ActorStatus, wire.ActorStatus(1, 2, 3, 4, 5, 1.0, [[1.0, 10]]),
     {"episode_returns": [[math.nan, 10]]}, "episode return"),
    (wire.ActorStatus, wire.ActorStatus(1, 2, 3, 4, 5, 1.0, []), {"steps_per_s": math.inf}, "steps_per_s"),
    (wire.EvalResult, wire.EvalResult(10, 1, [1.0]), {"returns": [1.0, math.inf]}, "returns"),
    (wire.EvalResult, wire.EvalResult(10, 1, [1.0]), {"returns": ["1.0"]}, "returns"),
    (wire.Weights, wire.Weights(1, 1, 0, {}), {"tensors": {"w": ["<q9", [1], b"\0" * 4]}}, "dtype"),
    (wire.Weights, wire.Weights(1, 1, 0, {}), {"tensors": {"w": ["<f4", [1], _f4(math.nan)]}}, "non-finite"),
    # finite as float64, inf once loaded into float32 parameters
    (wire.Weights, wire.Weights(1, 1, 0, {}), {"tensors": {"w": ["<f8", [1], np.float64(1e39).tobytes()]}},
     "beyond"),
    (wire.Weights, wire.Weights(1, 1, 0, {}), {"tensors": {"w": ["<f4", [2**62, 2**62], b""]}}, "shape"),
])
def test_request_and_report_values_are_checked(cls, msg, fields, match):
    assert wire.decode(wire.encode(msg), cls, BOUNDS) == msg
    with pytest.raises(wire.WireError, match=match):
        wire.decode(_with(msg, **fields), cls, BOUNDS)


def test_sample_replies_are_checked_against_the_run(tmp_path):
    svc = make_service(tmp_path, no_rate_limit=True)
    svc.insert_batch(batch(n=5)[0])
    reply = svc.sample(wire.SampleRequest(4, 0.0))
    assert wire.decode(wire.encode(reply), wire.SampleReply, BOUNDS).ok
    for field, value in (("reward", _f4(1, 1, 1, 1e30)), ("discount", _f4(1, 1, 1, 2)),
                         ("window_shape", [4, 9, 16, 16]), ("intrinsic", _f4(1, 1, 1, math.inf))):
        with pytest.raises(wire.WireError):
            wire.decode(_with(reply, **{field: value}), wire.SampleReply, BOUNDS)
    svc.store.close()


def test_a_nan_wait_does_not_escape_the_cap(tmp_path):
    svc = make_service(tmp_path)  # warm-up not reached: a request waits its wait_s out
    req = wire.SampleRequest(4, 1.0)
    req.wait_s = math.nan  # what a decoder without value checks let through
    assert not svc.sample(req).ok  # returns at once (NaN is no wait), never blocks for ever
    svc.store.close()


def test_a_bad_insert_is_refused_before_it_queues_behind_the_rate_limiter(tmp_path):
    svc = make_service(tmp_path)  # no insert thread runs: anything queued would wait
    msg, _, _ = batch(n=3)
    svc._on_insert(_sample(_with(msg, rewards=_f4(3e38, 1, 1))))
    svc._on_insert(_sample(b"\xc1 not msgpack"))
    assert svc.invalid == 2 and svc._inserts.empty()
    svc._on_insert(_sample(wire.encode(msg)))
    assert svc._inserts.qsize() == 1
    svc.store.close()


def test_replay_callbacks_and_threads_survive_any_value(tmp_path):
    svc = make_service(tmp_path, no_rate_limit=True)
    svc.insert_batch(batch(n=5)[0])
    # an index the store has not reached: the store raises ValueError; the callback counts it
    svc._on_intrinsic(_sample(wire.encode(wire.SetIntrinsic(np.int64(99).tobytes(), _f4(0.5)))))
    assert svc.invalid == 1

    class Query:
        key_expr = "q"
        replied: list = []

        def reply(self, key, payload):  # noqa: ANN001
            self.replied.append(("ok", payload))

        def reply_err(self, payload):  # noqa: ANN001
            self.replied.append(("err", payload))

        def drop(self):
            pass

    def boom(req):  # noqa: ANN001
        raise OverflowError("what no check foresaw")

    queries: queue.Queue = queue.Queue()
    for _ in range(2):
        queries.put((Query(), wire.UnscoredRequest(0, 4)))
    answers = iter([boom, svc.unscored])

    def answer(req):  # noqa: ANN001
        f = next(answers)
        if f == svc.unscored:
            svc.stop.set("test done")  # the loop ends after this one
        return f(req)

    svc._serve_loop(queries, answer)
    assert [kind for kind, _ in Query.replied] == ["err", "ok"]  # it survived the first and went on
    assert svc.invalid == 2
    svc.store.close()


def test_a_lower_reward_bound_refuses_rewards_but_not_the_scores_the_learner_clips_to_the_wire(
    tmp_path,
):
    """--max-abs-reward 10: a reward of 50 is refused; a score of 50 (within the wire's bound, the
    scorer's clip) is stored, or its rows would stay unscored and be scored again for ever."""
    svc = make_service(tmp_path, no_rate_limit=True, max_abs_reward=10.0)
    msg, _, _ = batch(n=3)
    svc._on_insert(_sample(_with(msg, rewards=_f4(50, 1, 1))))
    assert svc.invalid == 1
    svc.insert_batch(batch(n=5)[0])
    svc._on_intrinsic(_sample(wire.encode(wire.SetIntrinsic(np.int64(1).tobytes(), _f4(50.0)))))
    assert svc.invalid == 1 and svc.store._intrinsic[1] == 50.0
    svc.store.close()


def test_weights_with_an_unknown_dtype_do_not_crash_an_actor():
    actor, learner = _agent(0), _agent(1)
    bad: list[str] = []
    sub = WeightsSubscriber(actor, bad.append)
    body = msgpack.unpackb(_message(learner, epoch=1, version=5), raw=False)
    name = next(iter(body["tensors"]))
    body["tensors"][name][0] = "<V7"
    sub.offer(msgpack.packb(body, use_bin_type=True))
    assert not sub.maybe_load() and len(bad) == 1 and sub.version is None
    body["tensors"][name][0] = "bfloat16"
    sub.offer(msgpack.packb(body, use_bin_type=True))
    assert not sub.maybe_load() and len(bad) == 2
    sub.offer(_message(learner, epoch=1, version=5))
    assert sub.maybe_load() and sub.version == 5


def test_float64_weights_beyond_float32s_range_are_refused_and_the_actor_keeps_its_own():
    actor, learner = _agent(0), _agent(1)
    bad: list[str] = []
    sub = WeightsSubscriber(actor, bad.append)
    body = msgpack.unpackb(_message(learner, epoch=1, version=5), raw=False)
    name, (dtype, shape, data) = next((k, v) for k, v in body["tensors"].items() if v[0] == "<f4")
    values = np.frombuffer(data, "<f4").astype("<f8")
    values[0] = 1e39
    body["tensors"][name] = ["<f8", shape, values.tobytes()]
    before = {k: v.clone() for k, v in actor.policy_state_dict().items()}
    sub.offer(msgpack.packb(body, use_bin_type=True))
    assert not sub.maybe_load() and len(bad) == 1 and sub.version is None
    assert all(v.equal(before[k]) for k, v in actor.policy_state_dict().items())


def test_weights_claiming_a_count_far_past_the_budget_are_refused_and_the_count_is_kept():
    """The subscriber keeps the largest learner count it has seen (an actor's warm-up ends by it, the
    evaluator evaluates at it): one count of 10**15 would have stood for the rest of the run."""
    actor, learner = _agent(0), _agent(1)
    bad: list[str] = []
    sub = WeightsSubscriber(actor, bad.append, steps=1000)
    sub.offer(_message(learner, epoch=1, version=5, env_steps=10**15))
    assert not sub.maybe_load() and "env_steps" in bad[0] and sub.env_steps == 0 and sub.version is None
    sub.offer(_message(learner, epoch=1, version=6, env_steps=900))
    assert sub.maybe_load() and sub.env_steps == 900


def test_an_actor_status_with_bad_entries_does_not_crash_the_learner():
    learner = Learner.__new__(Learner)  # the callbacks need the board, the queue, the log and the bounds
    learner.core = SimpleNamespace(board=StatusBoard())
    learner._episodes = queue.Queue()
    learner.log = Log("learner")
    learner.bounds = BOUNDS
    good = wire.ActorStatus(1, 2, 30, 1, 5, 1.0, [[12.5, 10]])
    for entries in ([["x", 10]], [[math.nan, 10]], [[1.0, "10"]], [[1.0]], [None]):
        learner._on_actor_status(_sample(_with(good, episode_returns=entries)))
    learner._on_eval(_sample(_with(wire.EvalResult(10, 1, [1.0]), returns=[math.inf])))
    assert learner.core.board.invalid == 6 and learner._episodes.empty()
    learner._on_actor_status(_sample(wire.encode(good)))
    assert learner._episodes.get_nowait() == (12.5, 10)


def test_replay_stats_counting_past_the_step_budget_are_refused_and_env_steps_stay():
    """The learner keeps the largest count it has seen (and checkpoints it): one bad count would stay."""
    learner = Learner.__new__(Learner)
    learner.core = SimpleNamespace(board=StatusBoard())
    learner.log = Log("learner")
    learner.bounds = wire.Bounds.of(SPEC, steps=200)
    learner._on_stats(_sample(wire.encode(wire.ReplayStats(60, 1, 2**61, 60, 0, 0, 0, False))))
    assert learner.core.board.invalid == 1 and learner.core.board.env_steps == 0
    learner._on_stats(_sample(wire.encode(wire.ReplayStats(60, 1, 61, 61, 0, 0, 0, False))))
    assert learner.core.board.invalid == 1 and learner.core.board.env_steps == 61


def test_a_bad_stop_message_is_counted_and_a_good_one_stops_the_service(tmp_path):
    svc = make_service(tmp_path)
    svc._on_stop(_sample(b"\xc1 not msgpack"))
    svc._on_stop(_sample(_with(wire.Stop("done"), reason=7)))  # a reason that is not a string
    assert svc.invalid == 2 and not svc.stop
    svc._on_stop(_sample(wire.encode(wire.Stop("operator"))))
    assert svc.stop.reason == "stop message: operator" and svc.invalid == 2
    svc.store.close()


def test_an_actor_reads_its_own_ids_tokens_and_refuses_malformed_ones():
    """Tokens under alive/actor/<id>/*: a malformed incarnation is counted invalid and stops nothing,
    an older one is logged once, a newer one stops this actor (it then exits 2)."""
    from services.actor.actor import ActorService
    from shared.service import StopFlag

    keys = wire.Keys("r1")
    logged: list[str] = []
    invalid: list[str] = []
    actor = SimpleNamespace(keys=keys, incarnation=100, actor_id=0, stop=StopFlag(), superseded_by=None,
                            _older_seen=set(), log=logged.append, _invalid=invalid.append)

    def token(tail: str, kind=zenoh.SampleKind.PUT) -> SimpleNamespace:
        return SimpleNamespace(kind=kind, key_expr=keys.alive("actor", 0) + "/" + tail)

    for tail in ("x", "1e9", "NaN", "-"):
        ActorService._on_same_id(actor, token(tail))
    assert len(invalid) == 4 and not actor.stop
    ActorService._on_same_id(actor, token("100"))  # its own token
    ActorService._on_same_id(actor, token("99"))
    ActorService._on_same_id(actor, token("99"))
    ActorService._on_same_id(actor, token("101", zenoh.SampleKind.DELETE))  # a newer one that went
    assert len(logged) == 1 and not actor.stop and actor.superseded_by is None
    ActorService._on_same_id(actor, token(str(2**40)))  # a huge incarnation is still a newer one
    assert actor.stop and actor.superseded_by == 2**40


def test_an_episode_its_environment_cannot_go_on_with_is_abandoned_and_the_actor_goes_on():
    """A diverged simulation (or a NaN action) ends that episode, not the actor's process (a restart
    would meet the same weights and the same fault)."""
    from services.actor.actor import ActorService
    from shared import envs
    from shared.service import Log, StopFlag

    stop, played = StopFlag(), []

    def episode() -> None:
        played.append(len(played))
        if len(played) == 1:
            raise envs.EnvFault("the simulation diverged: mjWARN_BADQACC")
        stop.set("test done")

    writer = SimpleNamespace(replay_done=False, wait_for_replay=lambda: None)
    actor = SimpleNamespace(stop=stop, writer=writer, _bridge_present=lambda: True, _episode=episode,
                            _note_fault=lambda: None, env_faults=0, log=Log("actor 0"))
    ActorService._act(actor)
    assert played == [0, 1] and actor.env_faults == 1


def test_an_eval_result_at_a_step_the_run_never_evaluates_is_refused_and_blocks_nothing(tmp_path):
    """A result recorded at a far step (or with the wrong number of episodes) would have held back
    every real evaluation after it: such a result is counted invalid, not recorded."""
    from tests.test_learner import core_on

    learner = Learner.__new__(Learner)
    learner.core = core = core_on(tmp_path)  # 200 steps, evaluations every 50, 2 episodes each
    learner._evals = queue.Queue()
    learner.log = Log("learner")
    learner.bounds = BOUNDS
    for bad in (wire.EvalResult(10**15, 1, [1.0, 2.0]), wire.EvalResult(37, 1, [1.0, 2.0]),
                wire.EvalResult(250, 1, [1.0, 2.0]), wire.EvalResult(50, 1, [1.0, 2.0, 3.0]),
                wire.EvalResult(50, 1, [1.0])):
        learner._on_eval(_sample(wire.encode(bad)))
    assert core.board.invalid == 5 and learner._evals.empty()
    learner._on_eval(_sample(wire.encode(wire.EvalResult(50, 1, [1.0, 2.0]))))
    assert core.record_eval(learner._evals.get_nowait())["mean"] == 1.5



@pytest.mark.parametrize(("flag", "value", "says"), [
    ("max_in_flight", 0, "--max-in-flight must be >= 1"), ("send_batch", 0, "--send-batch must be >= 1"),
    ("threads", 0, "--threads must be >= 1"), ("status_every_s", math.nan, "--status-every-s"),
    ("actor_device", "banana", "banana"),
])
def test_an_actor_flag_it_cannot_run_with_is_refused_up_front(flag, value, says):
    from services.actor.actor import ActorArgs, check_args
    from shared.service import bad_input_errors
    from tests.tiny import tiny_config

    with pytest.raises(bad_input_errors(), match=says):
        check_args(ActorArgs(config=tiny_config(), **{flag: value}))
