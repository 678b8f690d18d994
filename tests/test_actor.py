"""The actor's reported env-step rate."""

from services.actor.actor import StepRate


def test_step_rate_spans_backpressure_pauses_and_forgets_old_progress():
    rate = StepRate(start=0.0, window_s=10.0)
    for t in range(1, 6):  # 8 steps/s for 5 s
        assert rate.update(float(t), 8 * t) == 8.0
    # Held back by the replay for 3 s: the rate drops but does not read 0.
    assert rate.update(8.0, 40) == 5.0
    # Still paused 10 s later: nothing happened within the window.
    assert rate.update(18.0, 40) == 0.0
    assert rate.update(19.0, 46) == 6.0 / 11.0  # the window starts at the newest point >= 10 s old


def test_an_actor_id_the_replay_cannot_take_exits_2_with_the_reason_before_it_connects():
    """An id the replay refuses (negative, or past 32 bits) left the actor acting with every episode
    refused; a NASA_ACTOR_ID that is no integer was a traceback (exit 1, restarted in a loop)."""
    import os
    import subprocess
    import sys

    from nasa.up import free_port

    # No router listens there: the id, not the connection, must be the error.
    base = {**os.environ, "NASA_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}", "NASA_RUN_ID": "bad"}
    base.pop("NASA_ACTOR_ID", None)
    for flags, env, reason in (([], {"NASA_ACTOR_ID": "abc"}, "NASA_ACTOR_ID='abc' is not an integer"),
                               (["--actor-id", "-2"], {}, "--actor-id must be -1"),
                               (["--actor-id", str(2**31)], {}, "--actor-id must be -1")):
        proc = subprocess.run([sys.executable, "-m", "services.actor", *flags], env={**base, **env},
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert reason in proc.stderr and "Traceback" not in proc.stderr


def test_a_bridge_reply_with_a_safety_state_it_cannot_read_neither_ends_the_actor_nor_loses_its_heartbeat():
    """Over real Zenoh on loopback: a bridge refuses a reset with an info map of another layout (or a
    state far longer than a state name). The actor reports `unreadable` (or the state cut short)
    instead of raising out of its loop, and the learner takes the heartbeat with its episodes."""
    import queue

    import pytest

    from nasa.up import free_port
    from services.actor.actor import UNREADABLE_FAULT, ActorArgs, ActorService
    from services.robot_bridge.client import BridgeEnv, BridgeUnavailable
    from services.robot_bridge.server import BridgeServer
    from shared import wire
    from shared.env_loop import EnvLoop
    from shared.envs import FrameStack
    from shared.gripper.sim import ValveSim
    from shared.service import StopFlag
    from shared.zenoh_session import open_client, open_router
    from tests.tiny import tiny_run

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run = tiny_run("td3_ae", steps=500)
    keys = wire.Keys(f"t{free_port()}")
    sim = ValveSim("gripper-valve_reset", seed=7, render_quality="fast")
    heartbeats: queue.Queue = queue.Queue()

    def on_status(sample) -> None:  # noqa: ANN001 -- what the learner does with it
        try:
            heartbeats.put(wire.decode(sample.payload.to_bytes(), wire.ActorStatus, wire.Bounds(steps=500)))
        except wire.WireError as err:
            heartbeats.put(err)

    with (open_router(endpoint), open_client(endpoint) as bridge_session,
          open_client(endpoint) as actor_session, open_client(endpoint) as learner_session,
          BridgeServer(bridge_session, "g7", sim, "gripper-valve_reset", log=lambda _: None).serve(),
          learner_session.declare_subscriber(keys.actor_status(3), on_status)):
        actor = ActorService(ActorArgs(config=run.config, run_id=keys.run_id, actor_id=3), actor_session,
                             StopFlag(), run)
        env = BridgeEnv(actor_session, "g7", client="actor-3", timeout_s=30.0)
        actor.env = FrameStack(env, 3)
        actor.loop = EnvLoop(actor.env)
        for info, reported in (({"safety": "estop"}, UNREADABLE_FAULT),
                               ({"safety": {"errors": {"1": 5}}}, UNREADABLE_FAULT),
                               ({"safety": {"state": "x" * 500}}, "x" * wire.MAX_FAULT_TEXT)):
            refusal = wire.BridgeReply(False, "estop", 0, 0, [3, 84, 84], b"", 0.0, 1.0, False, False, info)
            key, payload = f"test/refusing_bridge/{len(str(info))}", wire.encode(refusal)
            answer = bridge_session.declare_queryable(key, lambda q, p=payload: q.reply(q.key_expr, p))
            try:
                env.keys.reset = key
                with pytest.raises(BridgeUnavailable, match="refused a reset"):
                    actor.loop.reset()
                actor._note_fault()  # what the actor's loop does with a refusal: no exception
            finally:
                answer.undeclare()
            actor._finished.append([12.5, 25])
            actor._publish_status()
            status = heartbeats.get(timeout=30.0)
            assert isinstance(status, wire.ActorStatus), status
            assert status.fault == reported and status.episode_returns == [[12.5, 25]]
    sim.close()


def test_an_actor_whose_every_batch_the_replay_refuses_stops_with_the_reason_and_its_count(tmp_path):
    """Over real Zenoh on loopback, with the real replay service: the replay has seen a newer
    incarnation of actor 3 than this one (the older one was superseded while cut off), so it refuses
    every episode this one begins. The actor used to act on for ever; it stops with the reason
    (ConfigError: exit 2, like being superseded), and its last heartbeat counts the refused batches."""
    import queue
    import threading
    import time

    import numpy as np
    import pytest

    from nasa.up import free_port
    from services.actor.actor import ActorArgs, ActorService
    from services.replay.service import ReplayArgs, ReplayService
    from shared import wire
    from shared.config import ConfigError
    from shared.service import StopFlag
    from shared.zenoh_session import open_client, open_router, token_up
    from tests.tiny import tiny_run

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run = tiny_run("td3_ae", steps=5000)
    keys = wire.Keys(f"t{free_port()}")
    heartbeats: queue.Queue = queue.Queue()
    replay_stop = StopFlag()
    with (open_router(endpoint), open_client(endpoint) as replay_session,
          open_client(endpoint) as actor_session, open_client(endpoint) as learner_session,
          learner_session.declare_subscriber(
              keys.actor_status(3),
              lambda s: heartbeats.put(wire.decode(s.payload.to_bytes(), wire.ActorStatus)))):
        replay = ReplayService(ReplayArgs(config=run.config, run_id=keys.run_id, data=tmp_path,
                                          camera_checked=True), replay_session, replay_stop, run)
        replay.store.begin_episode(np.zeros(run.spec.frame_shape, np.uint8), 3, 2**31 - 1)
        serving = threading.Thread(target=replay.run)
        serving.start()
        try:
            deadline = time.monotonic() + 30
            while not token_up(learner_session, keys.alive("replay", 0), timeout_s=1.0):
                assert time.monotonic() < deadline, "the replay never came up"
            actor = ActorService(ActorArgs(config=run.config, run_id=keys.run_id, actor_id=3, send_batch=4),
                                 actor_session, StopFlag(), run)
            # Only so that an actor that never gives up fails the test instead of hanging it.
            watchdog = threading.Timer(120.0, actor.stop.set, ["test watchdog"])
            watchdog.start()
            with pytest.raises(ConfigError, match="refuses every batch of actor id 3") as err:
                actor.run()
            watchdog.cancel()
            assert f"older than incarnation {2**31 - 1}" in str(err.value)
            assert replay.store.num_inserted == 0
            assert actor.writer.refused >= 3
            # The last heartbeat, sent as it stopped, carries them all (each arrives in order).
            while heartbeats.get(timeout=30).refused != actor.writer.refused:
                pass
        finally:
            replay_stop.set("test done")
            serving.join(15)


def test_two_launches_of_an_id_in_the_same_tenth_get_distinct_incarnations_the_later_one_newer(
        tmp_path, monkeypatch):
    """The incarnation was the time in tenths of a second alone: two launches of one id in the same
    tenth got the same one, neither stopped, and the replay took their two streams for one."""
    from types import SimpleNamespace

    import zenoh

    from services.actor.actor import ActorService, new_incarnation
    from shared import wire
    from shared.service import StopFlag

    monkeypatch.setattr(wire, "restart_stamp", lambda per_s, bits: 7000)  # one instant
    first, second = new_incarnation(3, tmp_path), new_incarnation(3, tmp_path)
    assert (first, second) == (7000, 7001)
    assert new_incarnation(4, tmp_path) == 7000  # another id: the time
    monkeypatch.setattr(wire, "restart_stamp", lambda per_s, bits: 9000)  # later: the time again
    assert new_incarnation(3, tmp_path) == 9000
    # The later launch is the newer: the earlier one, seeing its token, stops as superseded.
    keys = wire.Keys("t")
    older = SimpleNamespace(keys=keys, incarnation=first, actor_id=3, stop=StopFlag(), superseded_by=None,
                            _older_seen=set(), log=lambda _: None, _invalid=lambda _: None)
    token = SimpleNamespace(kind=zenoh.SampleKind.PUT, key_expr=keys.alive("actor", 3, second))
    ActorService._on_same_id(older, token)
    assert older.stop and older.superseded_by == second


def test_incarnations_made_at_once_by_several_processes_on_a_host_all_differ(tmp_path):
    """Real processes, each making incarnations of one id as fast as it can in one frozen instant."""
    import subprocess
    import sys

    code = ("import sys; from pathlib import Path; from shared import wire; "
            "wire.restart_stamp = lambda per_s, bits: 7000; "
            "from services.actor.actor import new_incarnation; "
            "print(*(new_incarnation(3, Path(sys.argv[1])) for _ in range(50)))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
             for _ in range(3)]
    made = [int(n) for p in procs for n in p.communicate(timeout=120)[0].split()]
    assert all(p.returncode == 0 for p in procs)
    assert len(made) == 150 and len(set(made)) == 150 and min(made) == 7000


def test_an_actor_on_a_bridge_another_client_holds_steps_nothing_and_says_so_once_per_holder(capfd):
    """Over real Zenoh on loopback: another client holds the bridge's gripper. The actor's every
    reset is refused (nothing steps, nothing is stored), named as the holder's, and the actor says
    so once per holder, not at every retry; the bridge names the actor by its id, run and host."""
    import os
    import socket

    import pytest
    from bridge_harness import HOLD_S, held_bridge

    from nasa.up import free_port
    from services.actor.actor import ActorArgs, ActorService
    from services.robot_bridge.client import BridgeEnv, BridgeHeld
    from shared import wire
    from shared.service import StopFlag
    from tests.tiny import tiny_gripper_run

    run = tiny_gripper_run(steps=500)
    keys = wire.Keys(f"t{free_port()}")
    with held_bridge("g8", "actor 0 of run elsewhere on x") as (bridge, actor_session, other_session):
        actor = ActorService(ActorArgs(config=run.config, run_id=keys.run_id, actor_id=3, bridge="g8"),
                             actor_session, StopFlag(), run)
        with actor.bridge:
            assert actor._connect()
            for holder in ("actor 0 of run elsewhere on x", "evaluator of run elsewhere on y"):
                if holder.startswith("evaluator"):  # the first holder hands the gripper on
                    bridge.hold.hold_s = 0.0
                    BridgeEnv(other_session, "g8", client=holder).reset()
                    bridge.hold.hold_s = HOLD_S
                for _ in range(3):  # what the actor's loop does: an episode, refused, a pause
                    with pytest.raises(BridgeHeld, match=f"held by {holder} \\(pid ") as refused:
                        actor._episode()
                    actor._paused(refused.value)
            # Its name to the bridge: its id, run and host (not its pid: a restart keeps it).
            assert actor.env.pixels.client == f"actor 3 of run {keys.run_id} on {socket.gethostname()}"
        assert actor.env_steps == 0 and bridge.step_index == 0  # nothing stepped while refused
    said = [line for line in capfd.readouterr().err.splitlines() if "until the gripper is free" in line]
    assert len(said) == 2, said
    assert "held by actor 0 of run elsewhere on x" in said[0] and "held by evaluator of run elsewhere on y" \
        in said[1] and f"(pid {os.getpid()})" in said[1]
