"""What the learner sees, step by step, against the NaSA-TD3 reference's training loop.

The reference (UoA-CARES/NaSA_TD3, `train_loop.py`) acts uniformly at random for steps
1..warmup, acts with the policy from step warmup + 1, scores each later transition when it is
stored (before that step's updates) and makes G updates after each of those steps. Its frame stack
starts an episode with the reset frame k times. These tests pin the same schedule in `nasa train`
and in an actor, and check that the two runners store the same transitions.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import torch

from nasa.train import Trainer
from services.actor import actor as actor_module
from services.actor.actor import ActorArgs, ActorService
from services.replay.service import ReplayArgs, ReplayService
from shared import wire
from shared.agents import make_agent
from shared.env_loop import EnvLoop
from shared.envs import EnvSpec, FrameStack
from shared.replay.adder import StoreAdder, ZenohWriter
from shared.replay.store import ReplayStore
from shared.run_config import RunConfig
from shared.schedule import stored_updates, total_updates, updates_due
from shared.service import Log, StopFlag
from tests.tiny import WARMUP, tiny_config, tiny_run


class CountingPixels:
    """Frames that name their episode and step; episodes of `length` steps ending at a time limit."""

    def __init__(self, shape: tuple[int, int, int], action_dim: int, length: int) -> None:
        self.frame_shape, self.action_dim, self.length = shape, action_dim, length
        self.episode, self.t = -1, 0

    def _frame(self) -> np.ndarray:
        frame = np.full(self.frame_shape, self.t, np.uint8)
        frame[0] = self.episode  # the first channel names the episode
        return frame

    def reset(self) -> tuple[np.ndarray, float, float, bool]:
        self.episode, self.t = self.episode + 1, 0
        return self._frame(), 0.0, 1.0, False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool]:
        self.t += 1
        return self._frame(), 0.5 * self.t + self.episode, 1.0, self.t == self.length

    def rng_state(self) -> dict:
        return {}

    def set_rng_state(self, state: dict) -> None:
        pass


def test_nasa_train_acts_uniformly_for_the_warm_up_then_scores_and_updates_g_times_after_each_step(
        tmp_path, monkeypatch):
    g, extra = 2, 3
    config = tiny_config(steps=WARMUP + extra, updates_per_step=g, eval_at_start=False, eval_every=1_000,
                         eval_episodes=1)
    config.env.action_repeat = 50  # 20-step episodes: an episode ends, and the final evaluation is short
    config.env.time_limit = "terminal"
    trainer = Trainer.create(config, tmp_path)
    events: list[tuple] = []
    store, agent, scorer = trainer.store, trainer.agent, trainer.scorer
    real_collect, real_update, real_score = actor_module.collect_action, agent.update, scorer.score_new

    def collect(agent_, obs, warming_up, rng, action_dim):  # noqa: ANN001, ANN202
        events.append(("act", warming_up, store.num_inserted, agent.num_updates))
        return real_collect(agent_, obs, warming_up, rng, action_dim)

    def score_new() -> int:
        events.append(("score", store.num_inserted, agent.num_updates))
        return real_score()

    def update(batch):  # noqa: ANN001, ANN202
        events.append(("update", store.num_inserted, agent.num_updates))
        return real_update(batch)

    monkeypatch.setattr("nasa.train.collect_action", collect)
    monkeypatch.setattr(agent, "update", update)
    monkeypatch.setattr(scorer, "score_new", score_new)
    trainer.run()

    expected: list[tuple] = []
    for step in range(1, WARMUP + extra + 1):  # the reference's total_step_counter
        warming_up = step <= WARMUP
        done = g * max(0, step - 1 - WARMUP)  # updates made before this step
        expected += [("act", warming_up, step - 1, done), ("score", step, done)]
        if not warming_up:
            expected += [("update", step, done + i) for i in range(g)]
    assert events == expected
    rows = store.get(np.arange(store.num_inserted))
    assert np.all(rows["intrinsic"][:WARMUP] == 0.0)  # no bonus stored before learning starts
    assert np.all(rows["intrinsic"][WARMUP:] != 0.0) and np.all(np.isfinite(rows["intrinsic"]))
    # The reference's done at the time limit, which ends the 20th step's episode.
    np.testing.assert_array_equal(np.flatnonzero(rows["discount"] == 0.0), [19])
    assert np.all((rows["discount"] == 0.0) | (rows["discount"] == 1.0))


def sac_ae_reference_events(steps: int, init_steps: int) -> list[tuple]:
    """SAC-AE's reference loop (denisyarats/pytorch_sac_ae, `train.py`) written out, for its steps
    0..steps - 1: ("act", at random, stored, updates made) as each step picks its action (at random
    before `init_steps`), then ("update", stored, updates made) for each of its updates: from
    `init_steps` on, `init_steps` of them at the step that ends the warm-up, one at every later one,
    each on the replay of the `stored` transitions of the steps before, as that step's own is stored
    after them."""
    events, made = [], 0
    for step in range(steps):
        events.append(("act", step < init_steps, step, made))
        if step >= init_steps:
            for _ in range(init_steps if step == init_steps else 1):
                events.append(("update", step, made))
                made += 1
    return events


def sac_ae_reference_counts(steps: int, init_steps: int) -> list[int]:
    """The updates SAC-AE's reference has made at the top of each of its steps 0..steps - 1, where it
    has stored that many transitions and its logging and evaluation of that step run, and, last, at
    the end of a run of `steps` steps."""
    events = sac_ae_reference_events(steps, init_steps)
    return [e[3] for e in events if e[0] == "act"] + [sum(e[0] == "update" for e in events)]


def sac_ae_run(out, steps: int, warmup: int = WARMUP) -> Trainer:  # noqa: ANN001
    """A tiny `nasa train --algo sac_ae` run of 20-step episodes, with no evaluation on the way."""
    config = tiny_config("sac_ae", steps=steps, warmup_steps=warmup, eval_at_start=False, eval_every=1_000,
                         eval_episodes=1)
    config.env.action_repeat = 50
    return Trainer.create(config, out)


def nasa_train_events(trainer: Trainer, monkeypatch) -> list[tuple]:  # noqa: ANN001
    """The run's steps as `sac_ae_reference_events` writes the reference's: filled in as it runs."""
    agent, store = trainer.agent, trainer.store
    events: list[tuple] = []
    real_collect, real_update = actor_module.collect_action, agent.update

    def collect(agent_, obs, warming_up, rng, action_dim):  # noqa: ANN001, ANN202
        events.append(("act", warming_up, store.num_inserted, agent.num_updates))
        return real_collect(agent_, obs, warming_up, rng, action_dim)

    def update(batch):  # noqa: ANN001, ANN202
        events.append(("update", store.num_inserted, agent.num_updates))
        return real_update(batch)

    monkeypatch.setattr("nasa.train.collect_action", collect)
    monkeypatch.setattr(agent, "update", update)
    return events


def test_nasa_train_acts_and_updates_on_the_rows_sac_aes_reference_does(tmp_path, monkeypatch):
    """--algo sac_ae: steps 1..warmup at random, the initial policy at the next, whose updates (the
    burst) come after its action and before its transition is stored, as each later step's one
    does: every update samples the replay SAC-AE's would, and every action is picked by the policy
    of as many updates."""
    steps = WARMUP + 3
    trainer = sac_ae_run(tmp_path, steps)
    assert trainer.config.warmup_burst and trainer.config.updates_per_step == 1  # --algo sac_ae's
    assert trainer.config.updates_before_store
    assert trainer.agent.burst_updates == WARMUP  # its actor steps by the burst's env step
    events = nasa_train_events(trainer, monkeypatch)
    trainer.run()
    assert events == sac_ae_reference_events(steps, WARMUP)
    reference = sac_ae_reference_counts(steps, WARMUP)
    assert trainer.agent.num_updates == reference[-1]
    # The count the learner aims at in nasa up, step by step, and the replay's rate limit: on n stored
    # transitions, the updates SAC-AE makes on at most n.
    assert [updates_due(n, trainer.config) for n in range(steps + 1)] == reference
    assert total_updates(trainer.config) == reference[-1]
    sampled = [e[1] for e in events if e[0] == "update"]
    assert [stored_updates(n, trainer.config) for n in range(steps)] == [
        sum(k <= n for k in sampled) for n in range(steps)]


def test_a_resumed_sac_ae_run_makes_the_burst_once(tmp_path):
    """Resumed from a checkpoint at the end of the warm-up, the run makes the burst; from one past
    it, not again."""
    steps = 2 * WARMUP + 3
    for checkpointed in (WARMUP, 2 * WARMUP):  # each an episode's end, where nasa train checkpoints
        out = tmp_path / str(checkpointed)
        sac_ae_run(out, checkpointed).run()
        resumed = Trainer.resume(out, steps=steps)
        assert resumed.counters.env_steps == checkpointed
        resumed.run()
        assert resumed.agent.num_updates == sac_ae_reference_counts(steps, WARMUP)[-1]


class LaggingAcks:
    """A replay whose acknowledgement of a batch lands only after the actor's next step: as on a
    real network, where the actor decides its next action before its last batch is acknowledged."""

    def __init__(self, writer: ZenohWriter) -> None:
        self.writer, self.stored, self.held = writer, 0, 0
        self.discounts: list[float] = []

    def put(self, payload: bytes) -> None:
        msg = wire.decode(payload, wire.TransitionBatch)
        self.discounts += wire.array(msg.discounts, "<f4", (msg.n,)).tolist()
        if self.held:
            self.stored += self.held
            data = wire.encode(wire.InsertAck(msg.actor_id, msg.incarnation, self.stored))
            self.writer._on_ack(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data)))
        self.held = msg.n


def lone_actor(monkeypatch, episode: int,
               **args: object) -> tuple[ActorService, LaggingAcks, list[tuple], bytes]:
    """An actor (td3_ae, terminal time limit; ActorArgs `args`) whose replay acknowledges late, on
    episodes of `episode` steps; the (warming_up, holds the learner's initial weights) of each action it
    takes; and the learner's first weights message."""
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)  # the actor's; not this process's
    run = tiny_run("td3_ae", steps=10_000)
    run.config.env.time_limit = "terminal"
    actor = ActorService(ActorArgs(config=run.config, run_id="warmup-test", actor_id=7, send_batch=1,
                                   max_in_flight=2, **args), None, StopFlag(), run)  # type: ignore[arg-type]
    actor.writer._publisher = replay = LaggingAcks(actor.writer)
    actor.writer.window.on_replay(True)
    actor.env = FrameStack(CountingPixels(run.spec.frame_shape, run.spec.action_dim, episode), 3)
    assert actor._connect()  # the actor's loop, with the run's time-limit handling
    torch.manual_seed(run.config.seed)  # as the learner does before it builds its agent
    learner = make_agent("td3_ae", run.spec.obs_shape, run.spec.action_dim, run.config.agent,
                         torch.device("cpu")).policy_state_dict()
    weights = wire.encode(wire.Weights(1, 0, 0, wire.pack_tensors(learner)))
    acted: list[tuple] = []
    real_collect = actor_module.collect_action

    def collect(agent, obs, warming_up, rng, action_dim):  # noqa: ANN001, ANN202
        held = agent.policy_state_dict()
        acted.append((warming_up, all(torch.equal(held[k], v) for k, v in learner.items())))
        return real_collect(agent, obs, warming_up, rng, action_dim)

    monkeypatch.setattr(actor_module, "collect_action", collect)
    return actor, replay, acted, weights


def test_a_lone_actor_takes_its_first_policy_step_right_after_the_warm_up_while_its_acks_lag(monkeypatch):
    actor, replay, acted, weights = lone_actor(monkeypatch, WARMUP + 5)
    actor.weights.offer(weights)
    actor._episode()
    warming = [w for w, _ in acted]
    # As in nasa train and the reference: steps 1..warmup uniform, the policy from step warmup + 1.
    assert warming == [True] * WARMUP + [False] * 5
    assert replay.discounts == [1.0] * (WARMUP + 4) + [0.0]  # the reference's done at the time limit


def test_an_actor_past_the_warm_up_acts_first_with_the_learners_initial_weights_not_its_own(monkeypatch):
    """The actor's own networks come from its own seed; the learner's initial policy is the one
    nasa train and the reference take their first policy steps with. Weights that come late are
    waited for, once."""
    actor, _, acted, weights = lone_actor(monkeypatch, WARMUP + 3)
    late = threading.Timer(0.3, actor.weights.offer, [weights])
    late.start()
    actor._episode()
    late.join()
    assert [w for w, _ in acted] == [True] * WARMUP + [False] * 3
    assert all(holds for _, holds in acted[WARMUP:])
    assert actor.policy_version == 0 and actor.env_steps == WARMUP + 3


def test_both_runners_store_the_transitions_the_frame_stack_showed(tmp_path):
    """nasa train (StoreAdder) and an actor (ZenohWriter to the replay service) store, for every
    transition, the frame stacks before and after it (the first of an episode stacked from its
    reset frame, the last with the final frame), its action, summed reward and the discount of
    the terminal time limit: the reference's (state, action, reward, next_state, done)."""
    shape, k, action_dim, length, episodes = (3, 8, 8), 3, 2, 10, 3  # an episode spans two chunks
    spec = EnvSpec(shape, k, action_dim)
    config = tiny_config("nasa_td3", steps=1_000)
    config.env.image_size, config.env.time_limit = shape[1], "terminal"
    run = RunConfig(config, spec)
    local = ReplayStore(1_000, shape, k, action_dim)
    service = ReplayService(ReplayArgs(config=config, data=tmp_path, no_rate_limit=True), None,  # type: ignore[arg-type]
                            StopFlag(), run)
    writer = ZenohWriter(None, wire.Keys("t"), actor_id=1, incarnation=1, frame_shape=shape, send_batch=3,
                         max_in_flight=2, stop=StopFlag(), log=Log("test"))

    class ToService:
        def put(self, payload: bytes) -> None:
            msg = wire.decode(payload, wire.TransitionBatch, service.bounds)
            assert service.insert_batch(msg) == msg.n
            data = wire.encode(wire.InsertAck(1, 1, service.store.num_inserted))
            writer._on_ack(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data)))

    writer._publisher = ToService()
    writer.window.on_replay(True)
    rng = np.random.default_rng(0)
    seen: list[tuple] = []  # (obs, action, reward, next_obs, discount) as the learner should see them
    loops = [EnvLoop(FrameStack(CountingPixels(shape, action_dim, length), k), adder, "terminal")
             for adder in (StoreAdder(local), writer)]
    for _ in range(episodes):
        steps = [loop.reset() for loop in loops]
        np.testing.assert_array_equal(steps[0].obs, np.concatenate([steps[0].frame] * k))
        while not steps[0].last:
            action = rng.uniform(-1, 1, action_dim).astype(np.float32)
            before = steps[0].obs
            steps = [loop.step(action) for loop in loops]
            seen.append((before, action, steps[0].reward, steps[0].obs, 0.0 if steps[0].last else 1.0))
    n = episodes * length
    assert local.num_inserted == service.store.num_inserted == n
    for store in (local, service.store):
        rows = store.get(np.arange(n))
        for i, (obs, action, reward, next_obs, discount) in enumerate(seen):
            np.testing.assert_array_equal(rows["obs"][i], obs, err_msg=f"obs of row {i}")
            np.testing.assert_array_equal(rows["next_obs"][i], next_obs, err_msg=f"next_obs of row {i}")
            np.testing.assert_array_equal(rows["action"][i], action)
            assert (rows["reward"][i], rows["discount"][i]) == (np.float32(reward), discount), i
    service.store.close()


def test_a_benchmarked_actor_without_a_learner_acts_with_its_own_networks_when_told_to(monkeypatch):
    actor, _, acted, _ = lone_actor(monkeypatch, WARMUP + 3, act_before_weights=True)
    actor._episode()  # no weights ever come: it does not wait for them
    assert [w for w, _ in acted] == [True] * WARMUP + [False] * 3
    assert actor.weights.version is None and actor.env_steps == WARMUP + 3
