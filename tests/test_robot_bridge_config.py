"""The gripper config file: the example loads, and each bad value is named in the error."""

import tomllib
from pathlib import Path

import pytest

from services.robot_bridge import config

EXAMPLE = Path(config.__file__).with_name("example.toml")


def example() -> dict:
    return tomllib.loads(EXAMPLE.read_text())


def test_the_example_loads() -> None:
    c = config.load(EXAMPLE)
    assert c.servos.ids == (1, 2, 3, 4) and c.angle.source == "aruco" and c.valve.id == 5
    assert c.safety.torque_guard is True


BAD = [
    ("bus", "baud", 12345, "bus.baud: 12345 is not an XL-320 baud rate"),
    ("bus", "port", "", "bus.port: must not be empty"),
    ("bus", "port", 3, "bus.port: must be a string"),
    ("bus", "latency_ms", 0, "bus.latency_ms"),
    ("servos", "ids", [1, 2, 3], "servos.ids: must list 4 values"),
    ("servos", "ids", [1, 2, 2, 4], "servos.ids: ids must differ"),
    ("servos", "ids", [1, 2, 3, 300], "servos.ids[3]: 300 is not a servo id"),
    ("servos", "min_step", [200, 200, 900, 200], "servos.min_step[2]: 900 is not below servos.max_step[2]"),
    ("servos", "max_step", [820, 820, 820, 2000], "servos.max_step[3]: 2000 is outside 0..1023"),
    ("servos", "home", [512, 100, 512, 820], "servos.home[1]: 100 is outside"),
    ("servos", "moving_speed", 0, "servos.moving_speed: 0 is outside 1..1023"),
    ("servos", "torque_limit", 5000, "servos.torque_limit: 5000 is outside 1..1023"),
    ("servos", "max_step_change", 0, "servos.max_step_change: must be >= 1"),
    ("servos", "settle_s", -1.0, "servos.settle_s"),
    ("servos", "speed", 3, "servos.speed: unknown field"),
    ("valve", "id", 3, "valve.id: 3 is also a finger servo"),
    ("camera", "index", -1, "camera.index: must be >= 0"),
    ("camera", "width", 0, "camera.width: must be >= 1"),
    ("camera", "image_size", "84", "camera.image_size: must be an integer"),
    ("camera", "valve_centre", [0.5, 2.0], "camera.valve_centre"),
    ("angle", "source", "encoder", "angle.source: 'encoder' is not one of aruco, servo"),
    ("angle", "direction", 2, "angle.direction: must be 1 or -1"),
    ("angle", "aruco_dictionary", "DICT_9X9", "angle.aruco_dictionary"),
    ("safety", "step_timeout_s", 0, "safety.step_timeout_s: must be a finite number > 0"),
    ("safety", "reboot_wait_s", float("nan"), "safety.reboot_wait_s: must be a finite number >= 0"),
    ("servos", "settle_s", float("inf"), "servos.settle_s: must be a finite number"),
    ("servos", "settle_s", 10.0, "servos.settle_s: 10.0 must be below safety.step_timeout_s"),
    ("safety", "watchdog_off_s", 1.0, "safety.watchdog_off_s: 1.0 is below safety.watchdog_hold_s"),
    ("safety", "bus_watchdog_ms", 100, "safety.bus_watchdog_ms: the XL-320 has no bus watchdog"),
    ("safety", "torque_guard", 1, "safety.torque_guard: must be true or false, got 1"),
]


@pytest.mark.parametrize(("section", "key", "value", "message"), BAD, ids=[f"{s}.{k}" for s, k, _, _ in BAD])
def test_each_bad_value_is_named(section: str, key: str, value: object, message: str) -> None:
    raw = example()
    raw[section][key] = value
    with pytest.raises(config.GripperConfigError) as err:
        config.parse(raw, "gripper.toml")
    assert any(message in p for p in err.value.problems), err.value.problems
    assert len(err.value.problems) == 1  # only the bad field is blamed


def test_every_bad_field_is_reported_at_once(tmp_path: Path) -> None:
    raw = example()
    raw["bus"]["baud"] = 1
    raw["angle"]["source"] = "laser"
    raw["extra"] = {}
    del raw["servos"]["ids"]
    with pytest.raises(config.GripperConfigError) as err:
        config.parse(raw, "gripper.toml")
    text = str(err.value)
    for name in ("bus.baud", "angle.source", "extra: unknown section", "servos.ids: missing"):
        assert name in text
    (tmp_path / "bad.toml").write_text("[bus\nport = ")
    with pytest.raises(config.GripperConfigError, match="cannot read"):
        config.load(tmp_path / "bad.toml")


def test_servo_angle_source_needs_a_valve_servo() -> None:
    raw = example()
    raw["angle"]["source"] = "servo"
    raw["valve"]["id"] = 0
    with pytest.raises(config.GripperConfigError, match="needs a valve servo"):
        config.parse(raw)


def test_an_infinite_watchdog_is_refused() -> None:
    raw = example()
    raw["safety"]["watchdog_hold_s"] = raw["safety"]["watchdog_off_s"] = float("inf")
    with pytest.raises(config.GripperConfigError) as err:
        config.parse(raw, "gripper.toml")
    blamed = {p.split(":")[0] for p in err.value.problems}
    assert blamed == {"safety.watchdog_hold_s", "safety.watchdog_off_s"}
