"""The environment's fault state and env step times, from the actor's heartbeat to /status, and
`nasa up --bridge`'s checks and children."""

from __future__ import annotations

from pathlib import Path

import msgpack
import pytest

from nasa.up import bridge_id, layout_of, parse_up, service_argv, with_bridges
from services.actor.actor import StepTimes
from services.learner.status import StatusBoard
from services.robot_bridge.client import fault_state
from shared import wire
from shared.config import ConfigError
from shared.envs import FrameStack
from shared.gripper.sim import ValveSim

EXAMPLE_TOML = str(Path(__file__).parents[1] / "services" / "robot_bridge" / "example.toml")
BUCKETS = len(wire.STEP_SECONDS_BUCKETS) + 1


def heartbeat(incarnation: int = 1, fault: str | None = None, counts: list | None = None,
              seconds: float = 0.0) -> wire.ActorStatus:
    """An ActorStatus as the learner receives it: encoded and decoded."""
    msg = wire.ActorStatus(3, incarnation, 40, 1, 7, 9.5, [], fault, counts or [], seconds)
    return wire.decode(wire.encode(msg), wire.ActorStatus)


def test_fault_state_names_the_bridges_safety_state_in_one_word() -> None:
    assert fault_state({}) == "ok" and fault_state({"safety": {"state": "ready"}}) == "ok"
    assert fault_state({"safety": {"state": "estop", "watchdog": "torque_off"}}) == "estop"
    assert fault_state({"safety": {"state": "waiting_for_operator"}}) == "waiting_for_operator"
    assert fault_state({"safety": {"state": "ready", "watchdog": "torque_off"}}) == "torque_off"
    assert fault_state({"safety": {"state": "ready", "errors": {"2": ["overload"]}}}) == "overload"
    assert fault_state({"safety": {"state": "ready", "errors": {"1": ["input voltage"]}}}) == "input_voltage"
    # Refused because another client holds the gripper: this actor's steps stop, and /status says why.
    assert fault_state({"holder": "actor 1 of run r on h", "safety": {"state": "ready"}}) == "held"


def test_step_times_count_each_step_in_its_prometheus_bucket() -> None:
    times = StepTimes()
    for seconds in (0.0004, 0.001, 0.003, 0.7, 60.0):
        times.observe(seconds)
    assert len(times.counts) == BUCKETS and sum(times.counts) == 5
    assert times.counts[0] == 2  # le 0.001 holds 0.001 itself
    assert times.counts[wire.STEP_SECONDS_BUCKETS.index(0.005)] == 1
    assert times.counts[wire.STEP_SECONDS_BUCKETS.index(1.0)] == 1 and times.counts[-1] == 1
    assert times.total_s == pytest.approx(60.7044)


def test_the_status_board_shows_each_actors_fault_and_step_times() -> None:
    board = StatusBoard()
    board.actor_alive(3, 1, True)
    counts = [0] * BUCKETS
    counts[3], counts[5] = 10, 2
    board.actor_status(heartbeat(fault="estop", counts=counts, seconds=0.11))
    a = board.snapshot()["actors"][0]
    assert a["fault"] == "estop"
    h = a["env_step_seconds"]
    assert h["count"] == 12 and h["sum"] == pytest.approx(0.11)
    assert h["le"]["0.005"] == 0 and h["le"]["0.01"] == 10 and h["le"]["0.05"] == 12 and h["le"]["+Inf"] == 12
    board.actor_status(heartbeat(fault="ok", counts=counts))
    assert board.snapshot()["actors"][0]["fault"] == "ok"
    # A suite task reports no fault; a heartbeat without step times shows none.
    board.actor_status(heartbeat(incarnation=2))
    a = board.snapshot()["actors"][0]
    assert a["incarnation"] == 2 and a["fault"] is None and a["env_step_seconds"] is None


def test_an_actor_status_without_the_new_fields_still_decodes() -> None:
    body = msgpack.unpackb(wire.encode(wire.ActorStatus(0, 1, 2, 3, 4, 5.0, [])))
    for key in ("fault", "step_counts", "step_seconds"):
        del body[key]
    msg = wire.decode(msgpack.packb(body), wire.ActorStatus)
    assert (msg.fault, msg.step_counts, msg.step_seconds) == (None, [], 0.0)


@pytest.mark.parametrize(("fields", "match"), [
    ({"step_counts": [1, 2]}, "buckets"),
    ({"step_counts": [-1] + [0] * (BUCKETS - 1)}, "outside|not counts"),
    ({"step_counts": [0.5] + [0] * (BUCKETS - 1)}, "not counts"),
    ({"step_seconds": -1.0}, "step_seconds"),
    ({"fault": "x" * 65}, "fault"),
    ({"fault": 7}, "fault"),
])
def test_bad_fault_and_step_time_fields_are_refused(fields: dict, match: str) -> None:
    body = msgpack.unpackb(wire.encode(wire.ActorStatus(0, 1, 2, 3, 4, 5.0, [], "ok", [0] * BUCKETS, 1.0)))
    body.update(fields)
    with pytest.raises(wire.WireError, match=match):
        wire.decode(msgpack.packb(body), wire.ActorStatus)


def test_an_environment_without_a_fault_state_reports_none() -> None:
    pixels = ValveSim("gripper-valve", 0, image_size=32, render_quality="fast")
    try:
        assert FrameStack(pixels, 3).fault() is None  # the stand-in in-process has no interlocks
    finally:
        pixels.close()


def test_nasa_up_bridge_checks_its_flags() -> None:
    with pytest.raises(ConfigError, match="not a task a robot bridge serves"):
        parse_up(["--task", "cartpole-balance", "--bridge", "stand-in"])
    with pytest.raises(ConfigError, match="needs --bridge-config"):
        parse_up(["--task", "gripper-valve", "--bridge", "hardware", "--actors", "1"])
    with pytest.raises(ConfigError, match="--actors 1"):
        parse_up(["--task", "gripper-valve", "--bridge", "hardware", "--bridge-config", EXAMPLE_TOML,
                  "--actors", "2"])
    hardware, _ = parse_up(["--task", "gripper-valve", "--bridge", "hardware",
                            "--bridge-config", EXAMPLE_TOML])
    one = layout_of(hardware, gpu=True, cores=16)  # the machine's choice yields to one gripper
    assert one.actors == 1 and not one.evaluator
    with pytest.raises(ConfigError, match="--action-repeat 1"):
        parse_up(["--task", "gripper-valve", "--bridge", "stand-in", "--action-repeat", "8"])
    with pytest.raises(ConfigError, match="for --bridge hardware"):
        parse_up(["--task", "gripper-valve", "--bridge-config", "g.toml"])
    for bridge in ("stand-in", "emulator"):  # the config of a real gripper, which these do not drive
        with pytest.raises(ConfigError, match=f"for --bridge hardware, not --bridge {bridge}"):
            parse_up(["--task", "gripper-valve", "--bridge", bridge, "--bridge-config", EXAMPLE_TOML])


def test_nasa_up_with_the_real_gripper_learns_at_its_cameras_image_size(tmp_path) -> None:
    hardware = ["--task", "gripper-valve", "--bridge", "hardware", "--bridge-config", EXAMPLE_TOML]
    cmd, preset = parse_up([*hardware, "--preset", "cpu-small"])  # the preset's gripper variant: 32
    assert preset == "cpu-small" and cmd.config.env.image_size == 84  # example.toml's camera.image_size
    assert cmd.config.agent.random_shift == 2  # the rest of the variant stays
    for given in (["--image-size", "32"], ["--image-size=48"], ["--image_size", "40"], ["--image_size=32"]):
        with pytest.raises(ConfigError, match=r"image size is (32|48|40) but the camera .* gives 84x84"):
            parse_up([*hardware, *given])
    same, _ = parse_up([*hardware, "--image-size", "84"])
    assert same.config.env.image_size == 84
    with pytest.raises(ConfigError, match="(?s)--bridge-config: .*cannot read"):
        parse_up([*hardware[:-1], str(tmp_path / "no.toml")])
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(EXAMPLE_TOML).read_text().replace("image_size = 84", "image_size = 0"))
    with pytest.raises(ConfigError, match="(?s)--bridge-config: .*camera.image_size: must be >= 1"):
        parse_up([*hardware[:-1], str(bad)])


def test_nasa_up_starts_a_bridge_per_actor_and_points_each_actor_at_its_own(tmp_path) -> None:
    cmd, _ = parse_up(["--task", "gripper-valve_reset", "--bridge", "emulator", "--actors", "2",
                       "--image-size", "32", "--render-quality", "fast", "--seed", "5"])
    argv = with_bridges(cmd, service_argv(cmd, tmp_path, layout_of(cmd, gpu=False)), "run1")
    names = list(argv)
    assert names[:2] == ["robot_bridge-0", "robot_bridge-1"] and "learner" in names and "replay" in names
    for i in range(2):
        bridge, actor = argv[f"robot_bridge-{i}"], argv[f"actor-{i}"]
        assert bridge[bridge.index("--bridge-id") + 1] == bridge_id("run1", i) == f"run1-{i}"
        assert bridge[bridge.index("--task") + 1] == "gripper-valve_reset" and "--emulate" in bridge
        assert bridge[bridge.index("--image-size") + 1] == "32"
        assert bridge[bridge.index("--camera-id") + 1] == "0"  # the run's camera, as in-process
        assert bridge[bridge.index("--seed") + 1] == str(5 + i)
        assert actor[-2:] == ["--bridge", f"run1-{i}"]
    evaluator, eval_bridge = argv["evaluator"], argv["robot_bridge-eval"]  # its own bridge, its own seed
    assert evaluator[-2:] == ["--bridge", "run1-eval"] and "--emulate" in eval_bridge
    assert eval_bridge[eval_bridge.index("--seed") + 1] == str(5 + 1_000_000)
    cmd.config.env.camera_id = 3  # whatever the run holds is what its bridges render from
    argv = with_bridges(cmd, service_argv(cmd, tmp_path, layout_of(cmd, gpu=False)), "run1")
    assert all(argv[name][argv[name].index("--camera-id") + 1] == "3" for name in argv if "bridge" in name)
    off, _ = parse_up(["--task", "gripper-valve"])
    lay = layout_of(off, gpu=False)
    assert with_bridges(off, service_argv(off, tmp_path, lay), "run1") == service_argv(off, tmp_path, lay)
