"""The weights subscriber: latest wins, older weights never replace newer ones, bad ones are counted."""

from __future__ import annotations

import time

import torch

from shared import wire
from shared.agents import make_agent
from shared.weights import WeightsSubscriber
from tests.tiny import tiny_run


def _agent(seed: int):  # noqa: ANN202
    run = tiny_run("td3_ae")
    torch.manual_seed(seed)
    c = run.config
    return make_agent(c.algo, run.spec.obs_shape, run.spec.action_dim, c.agent, torch.device("cpu"))


def _message(agent, epoch: int, version: int, env_steps: int = 0) -> bytes:  # noqa: ANN001
    return wire.encode(wire.Weights(epoch, version, env_steps, wire.pack_tensors(agent.policy_state_dict())))


def _same(a, b) -> bool:  # noqa: ANN001
    sa, sb = a.policy_state_dict(), b.policy_state_dict()
    return all(torch.equal(sa[k], sb[k]) for k in sa)


def test_the_newest_offer_is_loaded_once_and_older_weights_never_replace_it():
    actor, learner_a, learner_b = _agent(0), _agent(1), _agent(2)
    bad: list[str] = []
    sub = WeightsSubscriber(actor, bad.append)
    assert not sub.maybe_load() and sub.version is None
    sub.offer(_message(learner_b, epoch=5, version=1))
    sub.offer(_message(learner_a, epoch=5, version=3, env_steps=120))  # latest wins
    assert sub.maybe_load() and _same(actor, learner_a)
    assert (sub.version, sub.env_steps) == (3, 120)
    assert not sub.maybe_load()  # nothing new parked
    sub.offer(_message(learner_b, epoch=5, version=2))  # older than what it holds
    assert not sub.maybe_load() and _same(actor, learner_a)
    sub.offer(_message(learner_b, epoch=6, version=0))  # a restarted learner: a newer epoch wins
    assert sub.maybe_load() and _same(actor, learner_b) and sub.version == 0
    assert bad == []


def test_malformed_weights_are_reported_and_leave_the_agent_as_it_was():
    actor, other = _agent(0), _agent(1)
    before = {k: v.clone() for k, v in actor.policy_state_dict().items()}
    bad: list[str] = []
    sub = WeightsSubscriber(actor, bad.append)
    sub.offer(b"not msgpack at all")
    assert not sub.maybe_load()
    tensors = wire.pack_tensors(other.policy_state_dict())
    name = next(iter(tensors))
    tensors[name][1] = [1, 2, 3]  # a shape that does not match its bytes
    sub.offer(wire.encode(wire.Weights(1, 1, 0, tensors)))
    assert not sub.maybe_load()
    # Well-formed tensors, all of the right shapes but the last: the others must not load either.
    state = other.policy_state_dict()
    last = list(state)[-1]
    state[last] = torch.zeros(*state[last].shape, 2)
    sub.offer(wire.encode(wire.Weights(1, 2, 0, wire.pack_tensors(state))))
    assert not sub.maybe_load()
    missing = dict(list(other.policy_state_dict().items())[:-1])  # one network's tensor left out
    sub.offer(wire.encode(wire.Weights(1, 3, 0, wire.pack_tensors(missing))))
    assert not sub.maybe_load()
    assert len(bad) == 4 and sub.version is None and "expected" in bad[2] and "missing" in bad[3]
    assert all(torch.equal(before[k], v) for k, v in actor.policy_state_dict().items())


def test_a_subscriber_that_missed_the_only_publish_asks_for_the_latest_until_it_holds_weights():
    """The evaluator's weights come once per evaluation period: a process whose first query was
    answered before the learner held any, and whose subscription missed the publish, must not wait
    for the next period."""
    import zenoh

    from nasa.up import free_port
    from shared.zenoh_session import open_client, open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    keys = wire.Keys("weights-test")
    latest: list[bytes] = []
    answered: list[bool] = []  # per query the learner answered: with weights or not

    def answer(query: zenoh.Query) -> None:
        held = list(latest)
        if held:
            query.reply(keys.eval_weights_latest, held[0])
        answered.append(bool(held))
        query.drop()

    actor, learner = _agent(0), _agent(1)
    with (open_router(endpoint), open_client(endpoint) as at_learner, open_client(endpoint) as at_evaluator,
          at_learner.declare_queryable(keys.eval_weights_latest, answer)):
        sub = WeightsSubscriber(actor, lambda what: None).subscribe(
            at_evaluator, keys.eval_weights, keys.eval_weights_latest)
        with sub:
            deadline = time.monotonic() + 10.0
            while not answered:  # the first query, answered with nothing
                assert not sub.maybe_load()
                assert time.monotonic() < deadline, "the learner was never asked"
                time.sleep(0.05)
            latest.append(_message(learner, epoch=1, version=0))  # held now, never published
            deadline = time.monotonic() + 10.0
            while not sub.maybe_load():
                assert time.monotonic() < deadline, "the subscriber never asked again"
                time.sleep(0.05)
            assert sub.version == 0 and _same(actor, learner)
            assert answered[0] is False and True in answered  # loaded from a later query
