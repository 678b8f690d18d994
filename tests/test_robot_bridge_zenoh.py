"""The bridge over real Zenoh on loopback: the stand-in behind it, BridgeEnv in front."""

import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import msgpack
import numpy as np
import pytest
import zenoh

from nasa.up import free_port
from services.robot_bridge import operate
from services.robot_bridge.client import BridgeEnv, BridgeHeld, BridgeUnavailable
from services.robot_bridge.server import ESTOP_REASON_CHARS, BridgeServer
from shared import wire
from shared.envs import FrameStack
from shared.evaluation import draws_restarter
from shared.gripper.sim import EPISODE_STEPS, ValveSim, angle_distance
from shared.zenoh_session import open_client, open_router, token_up

TASK = "gripper-valve_reset"


def wait_until(condition: Callable[[], bool], deadline_s: float = 20.0) -> None:
    end = time.monotonic() + deadline_s
    while not condition():
        assert time.monotonic() < end, "condition never held"
        time.sleep(0.02)


@contextlib.contextmanager
def stand_in_bridge(session, bridge_id: str, **settings: object) -> Iterator[BridgeServer]:  # noqa: ANN001
    """A bridge serving the gripper stand-in on `session`, closed after the block; `settings`
    (`log`, `hold_s`) go to BridgeServer."""
    sim = ValveSim("gripper-valve", seed=1, render_quality="fast")
    server = BridgeServer(session, bridge_id, sim, "gripper-valve", **{"log": lambda _: None, **settings})
    try:
        with server.serve():
            yield server
    finally:
        sim.close()


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def sessions(endpoint: str):
    with open_router(endpoint), open_client(endpoint) as bridge, open_client(endpoint) as actor:
        yield bridge, actor


def test_the_bridge_is_transparent_for_the_stand_in(sessions) -> None:
    bridge_session, actor_session = sessions
    sim = ValveSim(TASK, seed=7, render_quality="fast")
    local = ValveSim(TASK, seed=7, render_quality="fast")
    server = BridgeServer(bridge_session, "g1", sim, TASK, log=lambda _: None)
    try:
        with server.serve():
            env = BridgeEnv(actor_session, "g1", client="actor-0", timeout_s=30.0)
            assert (env.task, env.action_dim, env.image_size) == (TASK, 4, 84) and env.alive()
            stacked = FrameStack(env, 3)  # what the actor holds
            ts = stacked.reset()
            frame, _, _, _ = local.reset()
            assert ts.obs.shape == (9, 84, 84) and np.array_equal(ts.frame, frame)
            actions = np.random.default_rng(0).uniform(-1, 1, size=(EPISODE_STEPS, 4)).astype(np.float32)
            for i, action in enumerate(actions):
                ts = stacked.step(action)
                frame, reward, _, last = local.step(action.astype(np.float64))
                assert np.array_equal(ts.frame, frame) and ts.reward == reward and ts.last == last
                assert ts.last == (i == EPISODE_STEPS - 1)
            assert env.info["target_angle"] == local.target_angle and len(env.info["positions"]) == 4
            with pytest.raises(BridgeUnavailable, match="reset first"):
                env.step(np.zeros(4))  # past the end: refused, no transition
        # The bridge is gone: its token went with it, and a reset fails instead of hanging.
        wait_until(lambda: not env.alive())
        assert env.wait_alive(stop=lambda: True) is False  # an actor told to stop does not wait
        env.timeout_s = 2.0
        with pytest.raises(BridgeUnavailable):
            env.reset()
        # The bridge comes back (a restart): the paused client sees it and starts a new episode.
        restarted = ValveSim(TASK, seed=8, render_quality="fast")
        try:
            with BridgeServer(bridge_session, "g1", restarted, TASK, log=lambda _: None).serve():
                assert env.wait_alive(stop=lambda: False, poll_s=0.05)
                env.timeout_s = 30.0
                frame, _, _, last = env.reset()
                assert frame.shape == (3, 84, 84) and not last and env.episode == 0
        finally:
            restarted.close()
    finally:
        sim.close()
        local.close()


def test_a_reply_it_cannot_read_pauses_the_client_instead_of_crashing_it(sessions) -> None:
    """A garbled or mis-shaped reply is the bridge's fault: BridgeUnavailable (the actor abandons the
    episode and waits), not an error that ends the actor's process."""
    bridge_session, actor_session = sessions
    sim = ValveSim(TASK, seed=7, render_quality="fast")
    server = BridgeServer(bridge_session, "g5", sim, TASK, log=lambda _: None)
    good = wire.BridgeReply(True, "", 0, 0, [3, 84, 84], bytes(3 * 84 * 84), 0.0, 1.0, True, False, {})
    replies = {
        "garbage": b"\x00not a message",
        "shape": wire.encode(wire.BridgeReply(**{**vars(good), "frame_shape": [3, 64, 64],
                                                 "frame": bytes(3 * 64 * 64)})),
        "short": wire.encode(wire.BridgeReply(**{**vars(good), "frame": bytes(10)})),
    }
    try:
        with server.serve():
            env = BridgeEnv(actor_session, "g5", timeout_s=30.0)
            for name, payload in replies.items():
                key = f"test/bad_bridge/{name}"
                answer = bridge_session.declare_queryable(key, lambda q, p=payload: q.reply(q.key_expr, p))
                try:
                    env.keys.reset = key
                    with pytest.raises(BridgeUnavailable, match="bridge"):
                        env.reset()
                finally:
                    answer.undeclare()
    finally:
        sim.close()


def test_estop_ends_the_episode_and_refuses_resets_until_rearmed(sessions, endpoint: str) -> None:
    bridge_session, actor_session = sessions
    with stand_in_bridge(bridge_session, "g2") as server:
        env = BridgeEnv(actor_session, "g2", timeout_s=30.0)
        env.reset()
        env.step(np.zeros(4))
        keys = wire.BridgeKeys("g2")
        actor_session.put(keys.estop, wire.encode(wire.BridgeEStop(True, "test button")))
        wait_until(lambda: server.estopped)
        actor_session.put(keys.estop, wire.encode(wire.BridgeEStop(True, "pressed twice")))  # idempotent
        with pytest.raises(BridgeUnavailable, match="refused a step: e-stop"):
            env.step(np.zeros(4))  # not executed: no transition for the replay
        assert env.info["safety"]["state"] == "estop" and "e-stop" in env.info["reason"]
        with pytest.raises(BridgeUnavailable, match="e-stop"):
            env.reset()
        operate.send_estop("g2", False, "operator re-arm", endpoint)  # the operator's command
        wait_until(lambda: not server.estopped)
        env.reset()
        _, _, _, last = env.step(np.zeros(4))
        assert not last
        # A malformed request gets an error reply, not silence, and is counted.
        replies = list(actor_session.get(keys.step, payload=b"\x01garbage", timeout=10.0))
        assert replies and replies[0].err is not None and server.invalid == 1


def test_the_bridge_process_serves_and_estops_on_sigterm(sessions, endpoint: str) -> None:
    _, actor_session = sessions
    argv = ["--bridge-id", "p1", "--task", TASK, "--connect", endpoint]
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.robot_bridge", *argv],
        stderr=subprocess.PIPE, text=True, env={**os.environ, "MUJOCO_GL": "egl"},
    )
    try:
        wait_until(lambda: token_up(actor_session, wire.BridgeKeys("p1").alive), deadline_s=120.0)
        env = BridgeEnv(actor_session, "p1", timeout_s=60.0)
        frame, _, _, _ = env.reset()
        assert frame.shape == (3, 84, 84)
        _, reward, _, last = env.step(np.zeros(4, np.float32))
        assert -1.0 <= reward <= 0.0 and not last
        # A second process for the same bridge id would answer every step too (two grippers, one
        # policy): it refuses to serve, and the first serves on.
        again = subprocess.run([sys.executable, "-m", "services.robot_bridge", *argv], capture_output=True,
                               text=True, timeout=120, env={**os.environ, "MUJOCO_GL": "egl"})
        assert again.returncode == 2, again.stderr
        assert "bridge p1 is served by another process already" in again.stderr
        env.step(np.zeros(4, np.float32))
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM, err  # stopped from outside: not "finished"
        assert "e-stop: SIGTERM" in err
        wait_until(lambda: not env.alive())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_bad_gripper_config_exits_as_bad_input(tmp_path) -> None:
    bad = tmp_path / "gripper.toml"
    bad.write_text('[bus]\nport = "/dev/null"\nbaud = 7\n')
    done = subprocess.run(
        [sys.executable, "-m", "services.robot_bridge", "--config", str(bad)], capture_output=True, text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "bus.baud: 7" in done.stderr and "servos.ids: missing" in done.stderr


def test_the_camera_id_reaches_the_stand_in_and_is_refused_elsewhere() -> None:
    from services.robot_bridge.main import BridgeArgs, build_env

    sim = build_env(BridgeArgs(task=TASK, camera_id=0, image_size=32))
    try:
        assert sim.camera_id == 0
    finally:
        sim.close()
    # The stand-in's model has one camera: the run's camera id is checked there, not dropped.
    with pytest.raises(ValueError, match="camera_id 1 out of range"):
        build_env(BridgeArgs(task=TASK, camera_id=1, image_size=32))
    with pytest.raises(ValueError, match="--camera-id 1: the stand-in's camera"):
        build_env(BridgeArgs(task=TASK, camera_id=1, emulate=True))


class BrokenCamera(ValveSim):
    """A stand-in whose next step fails the way a camera that stopped would."""

    fail_next = False

    def step(self, action):
        if self.fail_next:
            self.fail_next = False
            raise RuntimeError("the camera returned no frame")
        return super().step(action)


def test_a_failing_step_is_an_error_reply_and_the_bridge_serves_on(sessions) -> None:
    bridge_session, actor_session = sessions
    sim = BrokenCamera("gripper-valve", seed=2, render_quality="fast")
    server = BridgeServer(bridge_session, "g3", sim, "gripper-valve", log=lambda _: None)
    try:
        with server.serve():
            env = BridgeEnv(actor_session, "g3", timeout_s=30.0)
            env.reset()
            sim.fail_next = True
            with pytest.raises(BridgeUnavailable, match="no frame"):
                env.step(np.zeros(4))
            env.reset()  # a new episode, as the actor starts after a bridge fault
            _, reward, _, last = env.step(np.zeros(4))
            assert not last and -1.0 <= reward <= 0.0
    finally:
        sim.close()


def test_a_rewind_replays_the_bridges_draws_from_where_it_started(sessions) -> None:
    """Evaluations of the same episodes through a bridge: the client cannot hold the bridge's draws,
    so it asks the bridge to put them back; the stand-in's valve goes back to where it started."""
    bridge_session, evaluator_session = sessions
    sim = ValveSim("gripper-valve", seed=5, image_size=32, render_quality="fast")
    actions = np.random.default_rng(1).uniform(-1, 1, size=(20, 4)).astype(np.float32)
    try:
        with BridgeServer(bridge_session, "g3", sim, "gripper-valve", log=lambda _: None).serve():
            env = FrameStack(BridgeEnv(evaluator_session, "g3", client="evaluator", timeout_s=30.0), 3)
            restart = draws_restarter(env, same_episodes=True)

            def evaluation() -> list[tuple[float, float]]:
                starts = []
                for _ in range(3):
                    env.reset()
                    starts.append((env.pixels.info["target_angle"], env.pixels.info["valve_angle"]))
                    for action in actions:  # the fingers push the valve round
                        env.step(action)
                return starts

            restart()
            first = evaluation()
            restart()
            again = evaluation()
            assert [t for t, _ in again] == [t for t, _ in first]
            for (_, valve), (_, valve_before) in zip(again, first, strict=True):
                assert angle_distance(valve, valve_before) < math.radians(1.0)
            assert angle_distance(first[0][1], 0.0) < math.radians(0.5)  # where the bridge started
            assert [t for t, _ in evaluation()] != [t for t, _ in first]  # no rewind: new draws
    finally:
        sim.close()


def test_no_router_is_named_in_one_line_within_the_timeout(endpoint: str) -> None:
    from shared.zenoh_session import RouterUnreachable

    began = time.monotonic()
    with pytest.raises(RouterUnreachable, match=f"no Zenoh router answered at {endpoint} within 0.5 s"):
        open_client(endpoint, timeout_s=0.5)
    assert time.monotonic() - began < 10.0


def test_an_estop_that_cannot_go_out_says_so_and_exits_1(endpoint: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "services.robot_bridge.operate", "estop", "--bridge-id", "g1",
         "--connect", endpoint], capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 1
    assert result.stderr.startswith(f"NOT sent: estop to bridge g1: no Zenoh router answered at {endpoint}")
    assert "Traceback" not in result.stderr and "sent estop" not in result.stdout


def test_a_stale_step_is_refused_and_leaves_the_live_episode_going() -> None:
    sim = ValveSim("gripper-valve", seed=1, render_quality="fast")
    server = BridgeServer(None, "g5", sim, "gripper-valve", log=lambda _: None)
    try:
        live = server.handle_reset(wire.BridgeReset("b"))
        action = np.zeros(4, "<f4").tobytes()
        stale = server.handle_step(wire.BridgeStep("b", live.episode - 1, 0, action))  # from before a restart
        assert not stale.ok and "stale step" in stale.reason
        again = server.handle_step(wire.BridgeStep("b", live.episode, 0, action))
        assert again.ok and not again.last and again.step == 1
        twice = server.handle_step(wire.BridgeStep("b", live.episode, 0, action))  # sent again
        assert not twice.ok and "stale step" in twice.reason and server.step_index == 1
    finally:
        sim.close()


def test_a_second_client_is_refused_naming_the_holder_while_the_first_steps_on(sessions, endpoint) -> None:
    """Two clients pointed at one bridge took turns resetting the gripper, each refusing the other's
    next step as stale, and neither recorded anything. The bridge serves the one it holds the
    gripper for; the other is refused, told who holds it; the holder restarted (its name again,
    another process) gets it back at once; anyone may still e-stop it."""
    bridge_session, actor_session = sessions
    said: list[str] = []
    with stand_in_bridge(bridge_session, "h1", log=said.append, hold_s=600.0) as server, \
            open_client(endpoint) as other_session:
        first = BridgeEnv(actor_session, "h1", client="actor 0 of run r on a", timeout_s=30.0)
        second = BridgeEnv(other_session, "h1", client="actor 1 of run r on b", timeout_s=30.0)
        first.reset()
        first.step(np.zeros(4))
        holder = rf"actor 0 of run r on a \(pid {os.getpid()}\)"
        with pytest.raises(BridgeHeld, match=rf"refused a reset: the gripper is held by {holder}, "
                                             r"last heard \d+\.\d s ago") as refused:
            second.reset()
        assert refused.value.holder == f"actor 0 of run r on a (pid {os.getpid()})"
        for i in range(2, 5):  # the holder's episode goes on as if the other were not there
            _, _, _, last = first.step(np.zeros(4))
            assert not last and server.step_index == i and server.episode == 0
        # An e-stop is anyone's to send: the other client's stops the gripper the first holds.
        button = wire.BridgeEStop(True, "the other's button")
        other_session.put(wire.BridgeKeys("h1").estop, wire.encode(button))
        wait_until(lambda: server.estopped)
        with pytest.raises(BridgeUnavailable, match="refused a step: e-stop: the other's button"):
            first.step(np.zeros(4))
        operate.send_estop("h1", False, "operator re-arm", endpoint)
        wait_until(lambda: not server.estopped)
        with pytest.raises(BridgeHeld):  # the re-arm hands the gripper to no one else
            second.reset()
        # The first restarted (`nasa up` restarts an actor with its id): the same name takes the
        # gripper back at once, its old episode is stale, and the other is still refused.
        restarted = BridgeEnv(other_session, "h1", client="actor 0 of run r on a", timeout_s=30.0)
        restarted.reset()
        restarted.step(np.zeros(4))
        with pytest.raises(BridgeUnavailable, match="stale step"):
            first.step(np.zeros(4))
        with pytest.raises(BridgeHeld, match=f"held by {holder}"):
            second.reset()
    held = [line for line in said if "gripper" in line]
    assert held == [f"gripper held by actor 0 of run r on a (pid {os.getpid()})"]  # said once


def test_a_holder_silent_for_the_hold_time_hands_the_gripper_to_the_next_client(sessions) -> None:
    bridge_session, actor_session = sessions
    said: list[str] = []
    with stand_in_bridge(bridge_session, "h2", log=said.append, hold_s=0.5):
        first = BridgeEnv(actor_session, "h2", client="actor 0 of run r on a", timeout_s=30.0)
        second = BridgeEnv(actor_session, "h2", client="evaluator of run r on b", timeout_s=30.0)
        first.reset()
        first.step(np.zeros(4))

        def taken() -> bool:  # the second asks until the first has been silent long enough
            try:
                second.reset()
            except BridgeHeld:
                return False
            return True

        wait_until(taken)
        second.step(np.zeros(4))
        with pytest.raises(BridgeHeld, match="held by evaluator of run r on b"):
            first.step(np.zeros(4))  # the first is back: its step is refused, its episode is over
        with pytest.raises(BridgeHeld, match="held by evaluator of run r on b"):
            first.reset()
    handed = [line for line in said if "handed over" in line]
    assert len(handed) == 1 and handed[0].startswith(
        f"gripper handed over from actor 0 of run r on a (pid {os.getpid()}) (silent for ")
    assert handed[0].endswith(f"to evaluator of run r on b (pid {os.getpid()})")


def test_an_older_client_naming_its_task_still_steps_alone_and_a_hold_time_must_be_positive() -> None:
    sim = ValveSim("gripper-valve", seed=1, render_quality="fast")
    server = BridgeServer(None, "h3", sim, "gripper-valve", log=lambda _: None)
    try:
        old_reset = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "bridge_reset", "client": "gripper-valve"})
        live = server.handle_reset(wire.decode(old_reset, wire.BridgeReset))  # no pid: an older client
        action = np.zeros(4, "<f4").tobytes()
        assert live.ok and server.handle_step(wire.BridgeStep("gripper-valve", live.episode, 0, action)).ok
        assert server.hold.holder() == "gripper-valve"
        # A name of any length the wire takes is cut in the refusal, which the client still reads.
        long_name = "x" * wire.MAX_TEXT
        refused = server.handle_reset(wire.BridgeReset(long_name, pid=7))
        assert not refused.ok and refused.info["holder"] == "gripper-valve"
        server.hold.hold_s = 0.0  # the older client gone silent: the long name takes the gripper
        assert server.handle_reset(wire.BridgeReset(long_name, pid=7)).ok
        server.hold.hold_s = 600.0
        refusal = server.handle_reset(wire.BridgeReset("gripper-valve"))
        refused = wire.decode(wire.encode(refusal), wire.BridgeReply)
        assert refused.info["holder"].endswith("... (pid 7)") and len(refused.reason) < wire.MAX_TEXT
    finally:
        sim.close()
    for bad in ("0", "-1", "inf", "nan"):
        done = subprocess.run([sys.executable, "-m", "services.robot_bridge", "--client-hold-s", bad],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and f"--client-hold-s must be a finite number > 0, got {float(bad)}" \
            in done.stderr, done.stderr


def estop_cli(bridge_id: str, endpoint: str, *extra: str,
              command: str = "estop") -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.robot_bridge.operate", command, "--bridge-id", bridge_id,
         "--connect", endpoint, *extra], capture_output=True, text=True, timeout=120,
    )


@pytest.fixture
def emulated_bridge(sessions):
    """The real gripper's code path (driver, interlocks) on the emulated bus, served as `e1`, reset
    once so its servos hold torque."""
    from services.robot_bridge.emulated import EmulatedGripper

    bridge_session, actor_session = sessions
    gripper = EmulatedGripper("gripper-valve", seed=0, image_size=32)
    server = BridgeServer(bridge_session, "e1", gripper, "gripper-valve", log=lambda _: None)
    try:
        with server.serve():
            BridgeEnv(actor_session, "e1", timeout_s=60.0).reset()
            yield server, gripper
    finally:
        gripper.close()


def torque(gripper) -> list[int]:  # noqa: ANN001
    from services.robot_bridge import xl320

    return [gripper.emulator.snapshot(sid, xl320.TORQUE_ENABLE) for sid in sorted(gripper.emulator.servos)]


def test_an_estop_is_confirmed_by_its_bridge_once_torque_is_off(emulated_bridge, endpoint: str) -> None:
    server, gripper = emulated_bridge
    assert torque(gripper)[:4] == [1, 1, 1, 1]
    result = estop_cli("e1", endpoint)
    # The emulated servos are read right after the command said `confirmed`, before anything else
    # could change them: torque was off when the bridge answered.
    assert torque(gripper) == [0] * 5
    assert result.returncode == 0, result.stderr
    by = f"{socket.gethostname()} pid {os.getpid()}"
    assert result.stdout.startswith(f"e-stop confirmed by bridge e1 ({by}): state estop, torque off")
    assert server.estopped
    rearmed = estop_cli("e1", endpoint, command="rearm")
    assert rearmed.returncode == 0, rearmed.stderr
    assert rearmed.stdout.startswith("re-arm confirmed by bridge e1") and "state recovering" in rearmed.stdout


def test_an_estop_of_the_stand_in_is_confirmed_as_stopped_not_as_torque_off(sessions, endpoint: str) -> None:
    """The stand-in has no servos: its confirmation must not tell the operator of a torque-off."""
    bridge_session, _ = sessions
    with stand_in_bridge(bridge_session, "s1") as server:
        result = estop_cli("s1", endpoint)
        assert result.returncode == 0, result.stderr
        by = f"{socket.gethostname()} pid {os.getpid()}"
        confirmed = f"e-stop confirmed by bridge s1 ({by}): state estop, stopped (the stand-in"
        assert result.stdout.startswith(confirmed), result.stdout
        assert "torque" not in result.stdout and server.estopped
    # A bridge older than the field does not say: it is taken for one with servos, as before.
    ack = wire.BridgeEStopAck("r", True, "estop", [], "h pid 1", stand_in=True)
    older = msgpack.unpackb(wire.encode(ack))
    del older["stand_in"]
    assert wire.decode(msgpack.packb(older), wire.BridgeEStopAck).stand_in is False


def test_an_estop_a_servo_did_not_hear_is_not_confirmed(emulated_bridge, endpoint: str) -> None:
    server, gripper = emulated_bridge
    gripper.emulator.kill(3)  # its cable cut: it holds torque, and cannot be told otherwise
    result = estop_cli("e1", endpoint)
    assert result.returncode == 1 and server.estopped
    assert "is e-stopped (state estop), but its torque-off did not reach servos [3]" in result.stderr
    assert "cut the servos' power" in result.stderr and torque(gripper) == [0, 0, 1, 0, 0]


def test_an_estop_no_bridge_hears_is_not_confirmed(sessions, endpoint: str) -> None:
    result = estop_cli("nobody", endpoint, "--wait-s", "1")
    assert result.returncode == 1
    assert result.stderr.startswith("NOT confirmed: estop went out, but no bridge nobody answered within 1 s")
    assert "cut the servos' power" in result.stderr and "confirmed by" not in result.stdout
    assert "Traceback" not in result.stderr


def test_a_wait_it_cannot_keep_is_refused_before_anything_is_sent() -> None:
    for bad in ("-1.0", "nan"):
        result = estop_cli("g1", "tcp/127.0.0.1:9", "--wait-s", bad)
        assert result.returncode == 2 and f"--wait-s {bad}: seconds, from 0 to 3600" in result.stderr
        assert "Traceback" not in result.stderr and "sent" not in result.stderr


def test_an_estop_to_another_id_is_not_confirmed_and_leaves_the_bridge_running(
        emulated_bridge, endpoint: str) -> None:
    server, gripper = emulated_bridge
    result = estop_cli("e2", endpoint, "--wait-s", "1")
    assert result.returncode == 1 and "no bridge e2 answered" in result.stderr
    assert not server.estopped and torque(gripper)[:4] == [1, 1, 1, 1]


def test_an_estop_ack_for_another_operator_is_not_taken(sessions, endpoint: str) -> None:
    """Two operators pressing at once: each waits for the answer to its own request."""
    bridge_session, _ = sessions
    keys = wire.BridgeKeys("g7")
    foreign = wire.BridgeEStopAck("someone-else", True, "estop", [], "elsewhere pid 1")

    def answer_others(sample) -> None:  # noqa: ANN001
        bridge_session.put(keys.estop_ack, wire.encode(foreign))

    with bridge_session.declare_subscriber(keys.estop, answer_others):
        assert operate.send_estop("g7", True, "test", endpoint, wait_s=1.0) is None


def test_an_answer_that_does_not_say_the_command_held_confirms_nothing() -> None:
    """A confirmation needs the bridge's state to say the command held: an e-stop answered with
    another state, or a re-arm answered `estop` or `waiting_for_operator`, is not confirmed (exit 1)."""
    for command, state in (("estop", "ready"), ("estop", "recovering"), ("rearm", "estop"),
                           ("rearm", "waiting_for_operator"), ("rearm", "x")):
        ack = wire.BridgeEStopAck("r", command == "estop", state, [], "h pid 1")
        line, confirmed = operate.report(command, "g1", ack, 5.0)
        assert not confirmed, line
        answered = f"NOT confirmed: bridge g1 (h pid 1) answered the {command} with state {state}"
        assert line.startswith(answered), line
    for command, state in (("estop", "estop"), ("rearm", "recovering"), ("rearm", "ready")):
        ack = wire.BridgeEStopAck("r", command == "estop", state, [], "h pid 1")
        assert operate.report(command, "g1", ack, 5.0)[1]
    unknown = operate.report("rearm", "g1", wire.BridgeEStopAck("r", False, "x", [], "h pid 1"), 5.0)[0]
    assert "does not know" in unknown and "recovery failed" not in unknown, unknown


def test_judging_an_answer_loads_no_servo_driver() -> None:
    """`estop`/`rearm` confirm a stop with the wire alone: the servo driver (pyserial, the Dynamixel
    SDK) is loaded only by the bridge and `calibrate`, so a confirmation never depends on it."""
    code = ("import sys; from services.robot_bridge import operate; from shared import wire; "
            "operate.report('rearm', 'g1', wire.BridgeEStopAck('r', False, 'ready', [], 'h'), 1.0); "
            "print(sorted(m for m in sys.modules if 'dynamixel' in m or m.startswith('serial')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_a_rearm_whose_recovery_failed_before_the_answer_is_not_confirmed(sessions, endpoint: str) -> None:
    """A bridge whose homing failed in the instant before it answered says `waiting_for_operator`
    (torque off, resets refused): `operate rearm` must not tell the operator the re-arm worked."""
    bridge_session, _ = sessions
    keys = wire.BridgeKeys("g12")

    def answer(sample) -> None:  # noqa: ANN001 -- a stand-in bridge, answering the command's own request
        sent = wire.decode(sample.payload.to_bytes(), wire.BridgeEStop)
        ack = wire.BridgeEStopAck(sent.request, sent.engage, "waiting_for_operator", [], "h pid 1")
        bridge_session.put(keys.estop_ack, wire.encode(ack))

    with bridge_session.declare_subscriber(keys.estop, answer):
        result = estop_cli("g12", endpoint, "--wait-s", "10", command="rearm")
    assert result.returncode == 1 and "confirmed by" not in result.stdout, result.stdout
    assert result.stderr.splitlines() == [
        "NOT confirmed: bridge g12 (h pid 1) answered the rearm with state waiting_for_operator: its "
        "recovery failed (torque off, resets refused): clear the fault its replies name under safety, "
        "then send the re-arm again"], result.stderr


def test_a_bridge_estopped_before_its_first_episode_refuses_in_a_reply_the_actor_reads(sessions) -> None:
    """E-stopped before any reset (an operator's stop before the actor joined): the first reset's
    refusal is read as one, with the e-stop's state, not as a malformed reply."""
    bridge_session, actor_session = sessions
    with stand_in_bridge(bridge_session, "g11") as server:
        env = BridgeEnv(actor_session, "g11", client="actor-0", timeout_s=30.0)
        server.estop("test")
        with pytest.raises(BridgeUnavailable, match="refused a reset: e-stop: test"):
            env.reset()
        assert env.fault() == "estop"


@pytest.mark.parametrize("sent", ["unreadable", "long reason"])
def test_an_estop_with_a_long_text_still_tells_the_actor_it_is_an_estop(sessions, sent: str) -> None:
    """The e-stop's reason goes into every refusal the bridge sends after it: a garbled message's
    error (which quotes what it was sent) or an operator's long reason must still leave that
    refusal readable, so the actor hears `estop`, not a malformed reply."""
    bridge_session, rogue = sessions
    with stand_in_bridge(bridge_session, "g10") as server:
        keys = wire.BridgeKeys("g10")
        env = BridgeEnv(rogue, "g10", client="actor-0", timeout_s=30.0)
        env.reset()
        if sent == "unreadable":
            payload = msgpack.packb({"v": wire.SCHEMA_VERSION, "t": "x" * 100_000})
        else:
            payload = wire.encode(wire.BridgeEStop(True, "r" * wire.MAX_TEXT, "tag"))
        rogue.put(keys.estop, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: server.estopped)
        with pytest.raises(BridgeUnavailable, match="refused a reset: e-stop: "):
            env.reset()
        assert env.fault() == "estop" and len(server.estop_reason) <= ESTOP_REASON_CHARS
        if sent == "long reason":
            assert server.estop_reason == "r" * (ESTOP_REASON_CHARS - 3) + "..."


def test_bad_estop_messages_fail_safe_and_bad_answers_confirm_nothing(sessions, endpoint: str) -> None:
    """The wire fuzzer's variants (tests/test_fuzz.py) of the e-stop's two messages: a bridge counts
    each malformed e-stop or re-arm and is stopped by it (fail safe: an unreadable message on the
    e-stop key may be a stop), never re-armed, and answers the operator after them; an operator takes
    no malformed answer as its confirmation, nor one to another command or one that says the bridge
    is not stopped, though each carries its own request."""
    from tests.test_fuzz import refused, variants

    bridge_session, rogue = sessions
    block = zenoh.CongestionControl.BLOCK
    with stand_in_bridge(bridge_session, "g8") as server:
        keys = wire.BridgeKeys("g8")
        for engage in (True, False):  # garbled e-stops while it runs, garbled re-arms while it is stopped
            bad = [p for p in variants(wire.BridgeEStop(engage, "fuzz", "tag"))
                   if refused(p, wire.BridgeEStop, wire.Bounds())]
            expected = server.invalid + len(bad)
            for p in bad:
                rogue.put(keys.estop, p, congestion_control=block)
            wait_until(lambda n=expected: server.invalid == n)
            assert len(bad) >= 30 and server.estopped
            assert "could not be read" in server.estop_reason, server.estop_reason
            ack = operate.send_estop("g8", engage, "test", endpoint, wait_s=10.0)  # the real command
            assert operate.report("estop" if engage else "rearm", "g8", ack, 10.0)[1]
            assert server.estopped is engage
    keys = wire.BridgeKeys("g9")  # no bridge: only the rogue answers
    forged: list[bytes] = []
    senders: list[threading.Thread] = []

    def forge(request: str) -> None:
        ack = wire.BridgeEStopAck(request, True, "estop", [], "rogue pid 1")
        body = msgpack.unpackb(wire.encode(ack))
        forged.extend(msgpack.packb({**body, **spoilt}) for spoilt in (
            {"state": "ready"}, {"engage": False, "state": "recovering"}, {"state": "x"},
            {"unreached": [[1.0]]}, {"unreached": [-1]}))
        forged.extend(p for p in variants(ack) if refused(p, wire.BridgeEStopAck, wire.Bounds()))
        for p in forged:
            rogue.put(keys.estop_ack, p, congestion_control=block)

    def answer(sample) -> None:  # noqa: ANN001 -- sent from a thread: a callback must not block
        request = wire.decode(sample.payload.to_bytes(), wire.BridgeEStop).request
        senders.append(threading.Thread(target=forge, args=(request,)))
        senders[-1].start()

    with rogue.declare_subscriber(keys.estop, answer):
        ack = operate.send_estop("g9", True, "test", endpoint, wait_s=2.0)
    for sender in senders:
        sender.join(timeout=60)
    assert len(senders) == 1 and len(forged) >= 30
    assert ack is None or not operate.report("estop", "g9", ack, 2.0)[1], ack


def test_a_bridge_id_that_is_no_id_is_refused_before_anything_is_sent(capsys) -> None:
    with pytest.raises(SystemExit) as exited:
        operate.main(["estop", "--bridge-id", "a/b", "--connect", "tcp/127.0.0.1:9"])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and "--bridge-id 'a/b': an id may hold only letters" in err, err


def test_a_new_bridge_turns_off_the_torque_a_killed_one_left_on(sessions) -> None:
    """What protects the servos after a containerised bridge dies (its guard dies with it) and
    Docker starts it again: the new bridge's watchdog, with no client and no reset."""
    import dataclasses

    from services.robot_bridge.emulated import EmulatedGripper

    bridge_session, _ = sessions
    gripper = EmulatedGripper("gripper-valve", seed=0, image_size=32)
    try:
        for sid in gripper.emulator.servos:  # as the killed bridge left them
            gripper.bus.set_torque(True, [sid])
        assert torque(gripper) == [1] * 5
        fingers = gripper.fingers
        fingers.safety = dataclasses.replace(fingers.safety, watchdog_hold_s=0.2, watchdog_off_s=0.5)
        with BridgeServer(bridge_session, "e3", gripper, "gripper-valve", log=lambda _: None).serve():
            wait_until(lambda: torque(gripper) == [0] * 5)
    finally:
        gripper.close()
