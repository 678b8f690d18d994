"""The evaluator's schedule and results, without Zenoh: which step is due, and what it publishes; and
the learner's evaluations between updates, which follow the same rules."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nasa.train import Trainer
from services.evaluator.evaluator import EvaluatorArgs, EvaluatorService
from services.learner.evaluation import BetweenUpdates
from shared import envs, wire
from shared.agents import make_agent
from shared.envs import EnvSpec
from shared.evaluation import draws_restarter
from shared.run_config import RunConfig
from shared.runlog import read_rows
from shared.service import StopFlag
from tests.tiny import tiny_config, tiny_gripper_run, tiny_run


def _service(**overrides: object) -> EvaluatorService:
    run = tiny_run("td3_ae", steps=500, **overrides)
    return EvaluatorService(EvaluatorArgs(config=run.config), None, StopFlag(), run)


def _weights(ev: EvaluatorService, version: int, env_steps: int = 0, epoch: int = 1) -> None:
    """The learner's evaluation weights of update `version`, sent at its env step `env_steps`."""
    tensors = wire.pack_tensors(ev.agent.policy_state_dict())
    ev.weights.offer(wire.encode(wire.Weights(epoch, version, env_steps, tensors)))


def test_step_zero_then_the_newest_multiple_reached_each_once_and_capped_at_the_budget():
    torch.manual_seed(0)
    ev = _service()
    assert ev.due() is None  # no weights yet
    _weights(ev, version=0)
    assert ev.due() == 0
    result = ev.evaluate(0)
    assert (result.step, result.policy_version, len(result.returns)) == (0, 0, 2)
    assert all(r >= 0.0 for r in result.returns)
    assert ev.due() is None
    _weights(ev, version=5, env_steps=49)
    assert ev.due() is None
    _weights(ev, version=6, env_steps=53)  # weights sent at step 50, not yet taken in
    _weights(ev, version=7, env_steps=130)  # slower than training: 50 is skipped, 100 is evaluated
    assert ev.due() == 100
    assert ev.evaluate(100).policy_version == 7  # the weights sent at that eval step
    _weights(ev, version=8, env_steps=530)  # past the budget, within the slack counts may have
    assert ev.due() == 500  # never past the run's budget
    ev.evaluate(500)
    assert ev.due() is None


def test_without_eval_at_start_the_first_evaluation_is_at_eval_every():
    ev = _service(eval_at_start=False)
    _weights(ev, version=0)
    assert ev.due() is None
    _weights(ev, version=1, env_steps=60)
    assert ev.due() == 50


def test_between_updates_the_learner_evaluates_the_same_steps_and_episodes_as_the_evaluator():
    """--eval-between-updates: the learner's own evaluations follow the evaluator's schedule, on an
    environment seeded as the evaluator's (and nasa train's), with the weights it trains."""
    torch.manual_seed(0)
    ev = _service()
    between = BetweenUpdates(ev.config, ev.agent, done_step=None)
    assert between.due(0) == 0 and between.due(49) == 0
    assert between.due(120) == 0  # before any update: the untrained policy, as step 0
    ours = between.run(0)
    _weights(ev, version=0)
    theirs = ev.evaluate(0)
    assert (ours.step, ours.policy_version) == (0, ev.agent.num_updates)
    assert ours.returns == theirs.returns  # the same episodes, the same policy: the same returns
    assert between.due(49) is None
    assert between.due(130) == 100  # slower than training: 50 is skipped, as the evaluator does
    assert between.due(10_000) is None  # the budget's step: the final policy's, not made yet
    assert between.due(10_000, final=True) == 500  # never past the run's budget
    # A resumed learner does not evaluate again a step its eval.csv holds.
    assert BetweenUpdates(ev.config, ev.agent, done_step=100).due(130) is None
    off = tiny_run("td3_ae", steps=500, eval_at_start=False).config
    assert BetweenUpdates(off, ev.agent, done_step=None).due(10) is None


def _eval_twice_in_each_process(tmp_path, same: bool) -> dict[str, tuple[list[float], ...]]:
    """Two evaluations of one fixed policy by the evaluator, the learner between updates and
    nasa train, on gripper-valve (each episode draws its target)."""
    config = tiny_config("td3_ae", steps=500, eval_episodes=3, eval_same_episodes=same)
    config.env.task = "gripper-valve"
    run = RunConfig(config, EnvSpec((3, 32, 32), 3, 4))
    torch.manual_seed(0)
    ev = EvaluatorService(EvaluatorArgs(config=config), None, StopFlag(), run)
    between = BetweenUpdates(config, ev.agent, done_step=None)
    trainer = Trainer.create(config, tmp_path / f"train-{same}")
    trainer.agent.load_policy_state_dict(ev.agent.policy_state_dict())
    out = {
        "evaluator": (ev.evaluate(0).returns, ev.evaluate(100).returns),
        "between_updates": (between.run(0).returns, between.run(100).returns),
    }
    trainer.run_evaluation()
    trainer.run_evaluation()
    rows = read_rows(tmp_path / f"train-{same}" / "eval.csv")
    out["nasa_train"] = tuple([float(row[f"return_{i}"]) for i in range(3)] for row in rows)
    return out


def test_with_eval_same_episodes_every_evaluation_plays_the_same_episodes(tmp_path):
    """The option in each process that evaluates: the same policy scores the same returns each
    time; without it (the reference's way) the second evaluation plays new targets."""
    same = _eval_twice_in_each_process(tmp_path, same=True)
    for first, second in same.values():
        assert first == second
    assert same["evaluator"] == same["between_updates"]
    assert same["nasa_train"][0] == pytest.approx(same["evaluator"][0], abs=1e-3)  # eval.csv rounds
    for first, second in _eval_twice_in_each_process(tmp_path, same=False).values():
        assert first != second


def test_a_suite_tasks_draws_restart_where_they_stood():
    env = envs.from_config(tiny_config(eval_same_episodes=True).env, seed=3)
    restart = draws_restarter(env, same_episodes=True)
    first = env.reset().obs
    assert not np.array_equal(env.reset().obs, first)  # the next episode starts elsewhere
    restart()
    assert np.array_equal(env.reset().obs, first)
    assert draws_restarter(env, same_episodes=False)() is None  # off: does nothing


def _suite_env(env: object) -> object:
    """The DeepMind Control Suite environment inside a PixelEnv."""
    while not hasattr(env, "_physics_error"):
        env = env._env
    return env._env


def _diverge_after(env: object, calls: int) -> None:
    """MuJoCo's PhysicsError (a diverged simulation) from the suite's step after `calls` steps."""
    from dm_control.rl.control import PhysicsError

    suite, left = _suite_env(env), [calls]
    step = suite.step

    def diverging(action: object) -> object:
        left[0] -= 1
        if left[0] < 0:
            raise PhysicsError("Physics state is invalid. Warning(s) raised: mjWARN_BADQACC")
        return step(action)

    suite.step = diverging


def test_a_diverged_simulation_skips_that_evaluation_and_the_evaluator_goes_on():
    ev = _service()
    _weights(ev, version=0)
    assert ev.evaluate(0) is not None
    _weights(ev, version=3, env_steps=60)
    _diverge_after(ev.env, 5)
    assert ev.evaluate(50) is None  # no row for step 50, and no crash
    assert ev.due() is None  # not played again: the same weights would diverge again
    _suite_env(ev.env).step = type(_suite_env(ev.env)).step.__get__(_suite_env(ev.env))
    _weights(ev, version=4, env_steps=110)
    result = ev.evaluate(ev.due())
    assert result is not None and result.step == 100 and len(result.returns) == 2


def test_a_policy_acting_nan_or_a_diverged_simulation_between_updates_is_not_the_learners_end(tmp_path):
    between = BetweenUpdates(tiny_config("td3_ae", steps=500), _service().agent, done_step=None)
    assert between.run(0).step == 0
    _diverge_after(between.env, 3)
    with pytest.raises(envs.EnvFault, match="diverged"):
        between.run(50)
    assert between.due(60) is None  # step 50 is done, without a row
    for p in between.agent.actor.parameters():
        p.data.fill_(float("nan"))
    with pytest.raises(envs.EnvFault, match="non-finite"):
        between.run(100)


def test_pictures_that_cannot_be_written_lose_nothing_but_themselves(tmp_path, monkeypatch):
    """The result is out before the pictures are made; a full disk fails them alone, leaving no
    temporary file, and the next evaluation goes on."""
    run = tiny_run("td3_ae", steps=500)
    args = EvaluatorArgs(config=run.config, data=tmp_path, video_every=1)
    ev = EvaluatorService(args, None, StopFlag(), run)
    try:
        _weights(ev, version=0)
        result = ev.evaluate(0)
        assert result is not None and result.step == 0

        def full(*_: object, **__: object) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr("PIL.Image.Image.save", full)
        ev.tap.autoencoder = ev.agent  # as when the weights carry the decoder
        ev.pictures(0)  # no exception
        assert not list((tmp_path / "media").glob("*.tmp*"))
        monkeypatch.undo()
        _weights(ev, version=2, env_steps=60)
        assert ev.evaluate(ev.due()).step == 50
        ev.pictures(50)
        assert (tmp_path / "media" / "eval_step_000000050.mp4").exists()
    finally:
        ev.media.close()


def test_a_damaged_media_manifest_is_moved_aside_and_a_new_one_started(tmp_path, capsys):
    from services.evaluator.media import EvalMedia

    (tmp_path / "media").mkdir()
    (tmp_path / "media" / "media.json").write_text('{"videos": [{"st')
    media = EvalMedia(tmp_path)
    media.close()
    assert media.manifest == {"autoencoder": None, "videos": []}
    assert (tmp_path / "media" / "media.json.damaged").read_text() == '{"videos": [{"st'
    assert "media.json is damaged" in capsys.readouterr().err


@pytest.mark.parametrize(("flag", "value", "says"), [
    ("view_frames", 0, "--view-frames 0"), ("eval_device", "banana", "banana"),
    ("threads", 0, "--threads 0"), ("video_every", -1, "--video-every -1"),
])
def test_an_evaluator_flag_it_cannot_run_with_is_refused_up_front(flag, value, says):
    from services.evaluator.evaluator import check_args
    from shared.service import bad_input_errors

    with pytest.raises(bad_input_errors(), match=says):
        check_args(EvaluatorArgs(config=tiny_config(), **{flag: value}))


def test_a_budget_that_is_no_multiple_of_eval_every_is_evaluated_at_its_end():
    """The final policy is evaluated however the budget falls, and by every runner alike."""
    from shared.evaluation import eval_due, is_eval_step

    c = tiny_config(steps=120)  # evaluations every 50
    assert [s for s in range(0, 200) if is_eval_step(s, c)] == [0, 50, 100, 120]
    assert eval_due(60, c, done=0) == 50 and eval_due(119, c, done=50) == 100
    assert eval_due(120, c, done=100) == 120 and eval_due(10_000, c, done=100) == 120
    assert eval_due(10_000, c, done=120) is None
    between = BetweenUpdates(c, _service().agent, done_step=100)
    assert between.due(125, final=True) == 120  # once the learner's updates are over


def test_a_restarted_learner_gets_the_newest_step_evaluated_again():
    """The result of step 100 went out while the learner was restarting (Zenoh keeps nothing):
    the restarted learner's first weights have step 100 played again."""
    ev = _service()
    _weights(ev, version=0)
    ev.evaluate(ev.due())
    _weights(ev, version=7, env_steps=130)
    assert ev.evaluate(ev.due()).step == 100  # ... and lost
    _weights(ev, version=8, env_steps=140)
    assert ev.due() is None  # the same learner: nothing new
    _weights(ev, version=3, env_steps=120, epoch=2)  # restarted from an earlier checkpoint
    assert ev.due() == 100
    ev.evaluate(100)
    _weights(ev, version=4, env_steps=145, epoch=2)
    assert ev.due() is None


def _evaluations(ev: EvaluatorService, steps: list[int]) -> list[list[float]]:
    out = []
    for version, step in enumerate(steps):
        _weights(ev, version=version, env_steps=step)
        out.append(ev.evaluate(ev.due()).returns)
    return out


def test_a_restarted_evaluator_plays_the_episodes_an_uninterrupted_one_would(tmp_path):
    """Its evaluation draws go on from where they stood (in its run folder), as nasa train's do."""
    def service(data):  # noqa: ANN001, ANN202
        torch.manual_seed(0)  # the same policy in each
        run = tiny_run("td3_ae", steps=500)
        args = EvaluatorArgs(config=run.config, data=data, video_every=0)
        return EvaluatorService(args, None, StopFlag(), run)

    straight = _evaluations(service(tmp_path / "straight"), [0, 50, 100])
    first = _evaluations(service(tmp_path / "restarted"), [0, 50])
    again = service(tmp_path / "restarted")  # the same folder, after a restart
    again.done = 50
    assert _evaluations(again, [100]) == straight[2:]
    assert first == straight[:2] and straight[2] != straight[0]


def test_a_resumed_learner_evaluating_between_updates_goes_on_with_its_draws(tmp_path):
    from tests.test_learner import core_on

    c = tiny_config("td3_ae", steps=500)
    torch.manual_seed(0)
    agent = _service().agent
    straight = BetweenUpdates(c, agent, done_step=None)
    returns = [straight.run(step).returns for step in (0, 50, 100)]
    before = BetweenUpdates(c, agent, done_step=None)
    before.run(0), before.run(50)
    core = core_on(tmp_path)  # the learner's checkpoint carries the draws
    core.eval_draws = before.draws
    assert core.save_checkpoint(1.0)
    restored = core_on(tmp_path).restored_eval_draws
    assert BetweenUpdates(c, agent, done_step=50, draws=restored).run(100).returns == returns[2]


def test_a_damaged_draws_file_is_said_and_the_draws_start_from_the_seed(tmp_path, capsys):
    (tmp_path / "evaluator").mkdir()
    (tmp_path / "evaluator" / "draws.pt").write_bytes(b"PK\x03\x04 half a file")
    run = tiny_run("td3_ae", steps=500)
    args = EvaluatorArgs(config=run.config, data=tmp_path, video_every=0)
    ev = EvaluatorService(args, None, StopFlag(), run)
    assert "cannot be read" in capsys.readouterr().err
    _weights(ev, version=0)
    assert ev.evaluate(0) is not None  # and the file is whole again
    ev.media.close()
    from shared import checkpoint

    assert checkpoint.load(tmp_path / "evaluator" / "draws.pt")["draws"]


def _counting_acts(ev: EvaluatorService, signal_at: int | None = None) -> list[int]:
    """Count the policy's actions; at the `signal_at`-th, SIGTERM this process, as `docker stop` does."""
    import os
    import signal

    acts: list[int] = []
    act = ev.agent.act

    def counting(*args: object, **kwargs: object) -> np.ndarray:
        acts.append(1)
        if len(acts) == signal_at:
            os.kill(os.getpid(), signal.SIGTERM)
        return act(*args, **kwargs)

    ev.agent.act = counting
    return acts


def test_sigterm_during_an_evaluation_ends_it_within_an_env_step_and_keeps_nothing_of_it(tmp_path):
    import signal

    run = tiny_run("td3_ae", steps=500)
    stop = StopFlag()
    ev = EvaluatorService(EvaluatorArgs(config=run.config, data=tmp_path, video_every=1), None, stop, run)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        _weights(ev, version=0)
        acts = _counting_acts(ev)
        assert ev.evaluate(ev.due()).step == 0
        per_evaluation = len(acts)  # two episodes of the same length
        ev.pictures(0)
        draws = (tmp_path / "evaluator" / "draws.pt").read_bytes()
        videos = sorted((tmp_path / "media").glob("*.mp4"))
        stop.install_signal_handlers()
        for signal_at in (3, per_evaluation // 2 + 3):  # in the first episode, and in the second
            _weights(ev, version=2, env_steps=60)
            acts = _counting_acts(ev, signal_at)
            assert ev.evaluate(ev.due()) is None
            assert len(acts) == signal_at and stop.signum == signal.SIGTERM  # not one step more
            ev.pictures(50)
            assert ev.done == 0 and ev.evaluations == 1  # played again by a restarted evaluator
            assert (tmp_path / "evaluator" / "draws.pt").read_bytes() == draws
            assert sorted((tmp_path / "media").glob("*.mp4")) == videos
            stop.event.clear()
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        ev.media.close()


def test_without_a_video_due_the_first_episode_keeps_only_the_frames_the_view_spreads_over_it(tmp_path):
    run = tiny_run("td3_ae", steps=500)
    args = EvaluatorArgs(config=run.config, data=tmp_path, view_frames=4)
    ev = EvaluatorService(args, None, StopFlag(), run)
    try:
        _weights(ev, version=0)
        draws = ev.env.rng_state()
        _, everything, cameras = ev._first_episode(keep=True, video=True)
        ev.env.set_rng_state(draws)  # the same episode again
        _, view, no_cameras = ev._first_episode(keep=True, video=False)
        assert len(everything) == len(cameras) > 9 and no_cameras == []
        assert 4 <= len(view) <= 2 * 4 + 1
        assert np.array_equal(view[0], everything[0]) and np.array_equal(view[-1], everything[-1])
    finally:
        ev.media.close()


@pytest.mark.parametrize("length", [1, 2, 8, 9, 10, 17, 125, 1000])
def test_spread_frames_hold_a_bounded_spread_from_first_to_last(length):
    from services.evaluator.evaluator import SpreadFrames

    frames = SpreadFrames(4)
    for i in range(length):
        frames.append(np.array(i))
    held = [int(f) for f in frames]
    assert len(held) == len(frames) <= 9 and held == sorted(set(held))
    assert held[0] == 0 and held[-1] == length - 1
    if length >= 9:  # no gap wider than twice an even spread's
        assert max(b - a for a, b in zip(held, held[1:], strict=False)) <= 2 * (length - 1) / 4


@pytest.mark.parametrize(("algo", "sent"), [("td3_ae", "view"), ("sac_ae", "view"), ("sac_ae", "decoder")])
def test_the_pictures_of_weights_that_carry_the_autoencoder(tmp_path, algo, sent):
    """The learner's evaluation weights carry the autoencoder's modules that the policy's lack
    (`view_state_dict`): the decoder, and SAC-AE's critic encoder, which its decoder reads. SAC-AE's
    evaluator reconstructed through an encoder it had not (and crashed at every evaluation's
    pictures); from a decoder alone (an older learner) it draws no view and still writes the video."""
    run = tiny_run(algo, steps=500)
    ev = EvaluatorService(EvaluatorArgs(config=run.config, data=tmp_path, video_every=1), None,
                          StopFlag(), run)
    source = make_agent(algo, run.spec.obs_shape, run.spec.action_dim, run.config.agent, torch.device("cpu"))
    try:
        state = source.policy_state_dict()
        if sent == "view":
            state |= source.view_state_dict()
        else:
            state |= {f"decoder.{k}": v for k, v in source.decoder.state_dict().items()}
        ev.weights.offer(wire.encode(wire.Weights(1, 0, 0, wire.pack_tensors(state))))
        ev.pictures(ev.evaluate(ev.due()).step)
        assert (tmp_path / "media" / "eval_step_000000000.mp4").exists()
        assert (tmp_path / "media" / "autoencoder.png").exists() == (sent == "view")
        if sent == "view":  # the source's own autoencoder, not the evaluator's initial one
            encoder, decoder = source.view_modules()
            for mine, theirs in zip(ev.tap.autoencoder, (encoder, decoder), strict=False):
                for a, b in zip(mine.parameters(), theirs.parameters(), strict=True):
                    assert torch.equal(a, b)
    finally:
        ev.media.close()


def test_the_video_cadence_goes_on_across_a_restart(tmp_path):
    run = tiny_run("td3_ae", steps=500)

    def evaluator() -> EvaluatorService:
        return EvaluatorService(EvaluatorArgs(config=run.config, data=tmp_path, video_every=2), None,
                                StopFlag(), run)

    def videos() -> list[str]:
        return sorted(p.name for p in (tmp_path / "media").glob("*.mp4"))

    ev = evaluator()
    for version, step in enumerate((0, 50, 100)):
        _weights(ev, version=version, env_steps=step)
        ev.pictures(ev.evaluate(ev.due()).step)
    ev.media.close()
    assert videos() == ["eval_step_000000000.mp4", "eval_step_000000100.mp4"]
    again = evaluator()  # restarted: the next video is due at step 200, not at once
    again.done = 100
    for version, step in enumerate((150, 200), 3):
        _weights(again, version=version, env_steps=step)
        again.pictures(again.evaluate(again.due()).step)
    again.media.close()
    assert videos() == ["eval_step_000000000.mp4", "eval_step_000000100.mp4", "eval_step_000000200.mp4"]


def test_the_media_manifest_is_strict_json(tmp_path):
    import json

    from services.evaluator.media import EvalMedia

    def refuse(word: str) -> None:
        raise ValueError(f"{word} in media.json")

    obs = np.random.default_rng(0).integers(0, 256, (3, 9, 32, 32), dtype=np.uint8)
    media = EvalMedia(tmp_path)
    media.video(None, obs, [None] * len(obs), step=100, episode_return=float("nan"))
    media.close()
    manifest = json.loads((tmp_path / "media" / "media.json").read_text(), parse_constant=refuse)
    assert manifest["videos"][0]["return"] is None and manifest["videos"][0]["step"] == 100


def test_a_manifest_entry_that_is_no_video_does_not_trip_the_next_video(tmp_path):
    from services.evaluator.media import EvalMedia

    (tmp_path / "media").mkdir()
    video = '{"step": 50, "file": "eval_step_000000050.mp4"}'
    (tmp_path / "media" / "media.json").write_text(f'{{"videos": [5, {video}]}}')
    obs = np.random.default_rng(0).integers(0, 256, (3, 9, 32, 32), dtype=np.uint8)
    media = EvalMedia(tmp_path)
    assert media.newest_video_step() == 50
    media.video(None, obs, [None] * len(obs), step=100, episode_return=1.0)
    media.close()
    assert [v["step"] for v in media.manifest["videos"]] == [50, 100]


def test_a_stop_after_the_result_is_out_makes_no_pictures(tmp_path):
    run = tiny_run("td3_ae", steps=500)
    stop = StopFlag()
    ev = EvaluatorService(EvaluatorArgs(config=run.config, data=tmp_path, video_every=1), None, stop, run)
    try:
        _weights(ev, version=0)
        assert ev.evaluate(ev.due()).step == 0
        ev.tap.autoencoder = ev.agent  # as when the weights carry the decoder
        stop.set("SIGTERM")
        ev.pictures(0)
        assert not (tmp_path / "media" / "autoencoder.png").exists()
        assert not list((tmp_path / "media").glob("*.mp4")) and ev.media.newest_video_step() is None
    finally:
        ev.media.close()


def test_the_evaluators_refused_writes_reach_the_learners_status_metrics_and_healthz(tmp_path, monkeypatch):
    """Over real Zenoh on loopback: pictures the disk refuses after a result went out are counted
    by the evaluator, sent to the learner with the result again (recorded once), and shown by the
    learner's /status `writes`, /metrics and /healthz; the next pictures that land clear `failing`."""
    import queue
    import time
    from types import SimpleNamespace

    from fastapi.testclient import TestClient

    from nasa.up import free_port
    from services.learner.health import degraded_reasons
    from services.learner.learner import Learner
    from services.learner.metrics import LearnerMetrics
    from services.learner.status_api import make_app
    from shared.service import Log
    from shared.zenoh_session import open_client, open_router, token_up
    from tests.test_learner import core_on

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run = tiny_run("nasa_td3", steps=200)
    keys = wire.Keys(f"t{free_port()}")
    with open_router(endpoint), open_client(endpoint) as evs, open_client(endpoint) as ls:
        learner = Learner.__new__(Learner)  # what _on_eval, _drain and status use
        learner.core = core_on(tmp_path / "learner")
        learner.keys, learner.bounds, learner.log = keys, wire.Bounds(), Log("learner")
        learner.client, learner.wall_s = SimpleNamespace(invalid=0), 1.0
        learner._scalars_at = time.monotonic()
        learner._evals, learner._episodes = queue.Queue(), queue.Queue()
        app = make_app(learner.status, lambda: [], metrics=LearnerMetrics(learner.status).render,
                       degraded=lambda: degraded_reasons(learner.core), render_every_s=0.0)
        client = TestClient(app)
        ev = EvaluatorService(EvaluatorArgs(config=run.config, data=tmp_path, run_id=keys.run_id,
                                            video_every=0), evs, StopFlag(), run)
        try:
            with (ls.declare_subscriber(keys.eval_result, learner._on_eval),
                  ls.liveliness().declare_token(keys.alive("learner", 0))):
                # Declared after the subscription, as the learner does: once the evaluator sees the
                # token, the router knows the subscription too.
                deadline = time.monotonic() + 30.0
                while not token_up(evs, keys.alive("learner", 0)):
                    assert time.monotonic() < deadline, "the learner's token never reached the evaluator"
                    time.sleep(0.05)

                def full(*_: object, **__: object) -> None:
                    raise OSError(28, "No space left on device")

                _weights(ev, version=0)
                target = ev.due()
                ev.tap.autoencoder = ev.agent  # as when the weights carry the decoder
                with monkeypatch.context() as disk:
                    disk.setattr("PIL.Image.Image.save", full)
                    ev.evaluate_and_send(target)
                deadline = time.monotonic() + 30.0
                while learner._evals.qsize() < 2 and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert learner._evals.qsize() == 2  # the result, then again with its pictures' failure
                learner._drain()
                assert len(read_rows(tmp_path / "learner" / "eval.csv")) == 1  # recorded once
                writes = client.get("/status").json()["writes"]
                assert writes["failed"] == {"evaluator/media": 1}
                assert writes["failing"] == ["evaluator/media"]
                assert writes["last_error"].startswith("evaluator/media: OSError")
                assert 'nasa_write_failures_total{file="evaluator/media"} 1.0' in client.get("/metrics").text
                health = client.get("/healthz")
                assert health.status_code == 200 and health.text.startswith(
                    "degraded: writes failing: evaluator/media")

                _weights(ev, version=2, env_steps=60)  # room again: step 50's pictures land
                target = ev.due()
                ev.tap.autoencoder = ev.agent
                ev.evaluate_and_send(target)
                deadline = time.monotonic() + 30.0
                while learner._evals.qsize() < 2 and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert learner._evals.qsize() == 2  # the result, then again: its pictures landed
                learner._drain()
                writes = client.get("/status").json()["writes"]
                assert writes["failed"] == {"evaluator/media": 1} and writes["failing"] == []
                assert client.get("/healthz").text == "ok\n"
        finally:
            ev.media.close()


def test_refused_write_counts_on_the_wire_are_checked():
    ok = wire.EvalResult(0, 0, [1.0], {"media": 2}, ["media"], "media: OSError")
    assert wire.decode(wire.encode(ok), wire.EvalResult) == ok
    old = wire.encode(wire.EvalResult(0, 0, [1.0]))  # an evaluator without them: none
    assert wire.decode(old, wire.EvalResult).write_failures == {}
    too_many = {f"k{i}": 1 for i in range(wire.MAX_WRITE_KINDS + 1)}
    for bad in ({"media": -1}, {"": 1}, {"media": True}, too_many):
        with pytest.raises(wire.WireError, match="write_failures"):
            wire.decode(wire.encode(wire.EvalResult(0, 0, [1.0], bad)), wire.EvalResult)
    with pytest.raises(wire.WireError, match="writes_failing"):
        wire.decode(wire.encode(wire.EvalResult(0, 0, [1.0], {}, ["media"])), wire.EvalResult)


def test_an_evaluator_on_a_bridge_another_client_holds_says_so_once_not_at_every_retry(capfd):
    """Over real Zenoh on loopback: another client holds the bridge's gripper. Each evaluation is
    abandoned (no result) and played again later; the evaluator says why once for that holder."""
    import socket

    from bridge_harness import held_bridge

    from nasa.up import free_port

    run = tiny_gripper_run(steps=500)
    keys = wire.Keys(f"t{free_port()}")
    with held_bridge("e9", "actor 0 of run elsewhere on x") as (server, eval_session, _):
        ev = EvaluatorService(EvaluatorArgs(config=run.config, run_id=keys.run_id, bridge="e9"),
                              eval_session, StopFlag(), run)
        _weights(ev, version=0)
        with ev.bridge:
            target = ev.due()
            assert [ev.evaluate(target) for _ in range(3)] == [None] * 3
            assert ev.env is None and ev.evaluations == 0
            server.hold.hold_s = 0.0  # the holder is silent from now on: the evaluator takes it
            assert ev.evaluate(target) is not None
            assert server.hold.client == f"evaluator of run {keys.run_id} on {socket.gethostname()}"
    said = [line for line in capfd.readouterr().err.splitlines() if "evaluation abandoned" in line]
    assert len(said) == 1 and "held by actor 0 of run elsewhere on x" in said[0], said
