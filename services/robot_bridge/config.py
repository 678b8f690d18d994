"""The gripper's config file (TOML): serial bus, servos, camera, angle source, safety limits.

`load(path)` reads and validates it, and raises one `GripperConfigError` that lists every bad
field by its dotted name (`servos.home[2]: 1100 is outside servos.min_step..max_step (200..820)`),
so an operator fixes the file in one pass. `example.toml` beside this module is a complete file.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.robot_bridge import xl320

BAUD_RATES = (9600, 57600, 115200, 1000000)  # what the XL-320 speaks
ANGLE_SOURCES = ("aruco", "servo")
ARUCO_DICTIONARIES = (
    "DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_5X5_100", "DICT_6X6_50", "DICT_ARUCO_ORIGINAL",
)
FINGER_SERVOS = 4


class GripperConfigError(ValueError):
    """A config file with bad fields; `problems` holds one line per field."""

    def __init__(self, path: str, problems: list[str]) -> None:
        super().__init__(f"{path}: {len(problems)} bad field(s):\n  " + "\n  ".join(problems))
        self.problems = problems


@dataclass(frozen=True)
class BusConfig:
    port: str
    baud: int = 1000000
    latency_ms: float = 16.0
    """The USB adapter's latency timer: the SDK waits twice this (plus transfer time) for a reply."""


@dataclass(frozen=True)
class ServoConfig:
    """The four finger servos, in action order (finger A base, A tip, B base, B tip)."""

    ids: tuple[int, ...]
    min_step: tuple[int, ...]
    max_step: tuple[int, ...]
    home: tuple[int, ...]
    moving_speed: int = 300
    torque_limit: int = 600
    max_step_change: int = 150
    """The most a goal may move from the previous goal in one env step (steps)."""
    settle_s: float = 0.3
    """How long the goals act before the frame of a step is taken."""


@dataclass(frozen=True)
class ValveServoConfig:
    """The servo under the valve (scenario 2); `id` 0 when there is none."""

    id: int = 0
    moving_speed: int = 200
    torque_limit: int = 500


@dataclass(frozen=True)
class CameraConfig:
    index: int = 0
    width: int = 640
    height: int = 480
    image_size: int = 84
    drop_frames: int = 4
    """Buffered frames read and dropped before each observation, so it is from after the action."""
    valve_centre: tuple[float, ...] = (0.5, 0.5)
    """Where the valve's axis is in the image (fractions of width, height): the target is drawn
    around it, since the policy sees only pixels."""
    target_radius: float = 0.35
    """The drawn target marker's distance from the valve centre, as a fraction of the image height."""


@dataclass(frozen=True)
class AngleConfig:
    source: str = "aruco"
    zero_deg: float = 0.0
    """Calibration: the raw reading (degrees) at which the valve is at angle 0."""
    direction: int = 1
    """+1 if the raw reading grows counter-clockwise as seen from the camera, else -1."""
    aruco_dictionary: str = "DICT_4X4_50"
    aruco_id: int = 0


@dataclass(frozen=True)
class SafetyConfig:
    step_timeout_s: float = 2.0
    watchdog_hold_s: float = 2.0
    """No command for this long: hold the present position."""
    watchdog_off_s: float = 10.0
    """No command for this long: torque off."""
    home_tolerance: int = 15
    """Steps within which homing counts as done (recovery's check)."""
    home_timeout_s: float = 5.0
    reboot_wait_s: float = 0.5
    torque_guard: bool = True
    """A process of its own (`guard.py`) turns torque off when the bridge dies without its clean stop."""


@dataclass(frozen=True)
class GripperConfig:
    bus: BusConfig
    servos: ServoConfig
    valve: ValveServoConfig = field(default_factory=ValveServoConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    angle: AngleConfig = field(default_factory=AngleConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)


# A setting copied from an X-series manual: refused with the reason, not as a typo.
NO_BUS_WATCHDOG = (
    "the XL-320 has no bus watchdog (the X-series' Bus Watchdog at address 98 is not in its control "
    "table); the bridge's own watchdog (safety.watchdog_hold_s, safety.watchdog_off_s), its "
    "torque-off on SIGTERM and its torque guard (safety.torque_guard), which turns torque off when "
    "the bridge is killed, are the stops"
)


def load(path: str | Path) -> GripperConfig:
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise GripperConfigError(str(path), [f"cannot read: {e}"]) from e
    return parse(raw, str(path))


def parse(raw: dict[str, Any], source: str = "<config>") -> GripperConfig:
    """Build and validate a config from a TOML table; every bad field is reported at once."""
    problems: list[str] = []
    sections = {
        "bus": BusConfig, "servos": ServoConfig, "valve": ValveServoConfig,
        "camera": CameraConfig, "angle": AngleConfig, "safety": SafetyConfig,
    }
    for name in raw:
        if name not in sections:
            problems.append(f"{name}: unknown section (known: {', '.join(sections)})")
    built: dict[str, Any] = {}
    for name, cls in sections.items():
        before = len(problems)
        section = _section(name, cls, raw.get(name), problems)
        built[name] = section if len(problems) == before else None
    # Values are checked in every section that parsed, so one pass reports every bad field.
    problems.extend(_check(**built))
    if problems:
        raise GripperConfigError(source, problems)
    return GripperConfig(**built)


def _section(name: str, cls: type, table: Any, problems: list[str]) -> Any:
    fields = cls.__dataclass_fields__
    if table is None:
        table = {}
    if not isinstance(table, dict):
        problems.append(f"{name}: must be a table, got {type(table).__name__}")
        return None
    values: dict[str, Any] = {}
    for key, value in table.items():
        if name == "safety" and key.startswith("bus_watchdog"):
            problems.append(f"{name}.{key}: {NO_BUS_WATCHDOG}")
            continue
        if key not in fields:
            problems.append(f"{name}.{key}: unknown field (known: {', '.join(fields)})")
            continue
        expected = fields[key].type
        values[key] = _typed(f"{name}.{key}", value, str(expected), problems)
    missing = dataclasses.MISSING
    for key, f in fields.items():
        if key not in values and f.default is missing and f.default_factory is missing:
            problems.append(f"{name}.{key}: missing (required)")
    try:
        return cls(**values)
    except TypeError:
        return None  # the missing/unknown fields are already reported


def _typed(name: str, value: Any, expected: str, problems: list[str]) -> Any:
    """Check a value against its field's annotation; tuples of ints come from TOML arrays."""
    if expected == "tuple[int, ...]":
        if not isinstance(value, list) or not all(type(v) is int for v in value):
            problems.append(f"{name}: must be an array of integers, got {value!r}")
            return ()
        return tuple(value)
    if expected == "tuple[float, ...]":
        if not isinstance(value, list) or not all(type(v) in (int, float) for v in value):
            problems.append(f"{name}: must be an array of numbers, got {value!r}")
            return ()
        return tuple(float(v) for v in value)
    if expected == "int" and (not isinstance(value, int) or isinstance(value, bool)):
        problems.append(f"{name}: must be an integer, got {value!r}")
    elif expected == "float" and (not isinstance(value, int | float) or isinstance(value, bool)):
        problems.append(f"{name}: must be a number, got {value!r}")
    elif expected == "str" and not isinstance(value, str):
        problems.append(f"{name}: must be a string, got {value!r}")
    elif expected == "bool" and not isinstance(value, bool):
        problems.append(f"{name}: must be true or false, got {value!r}")
    return float(value) if expected == "float" and isinstance(value, int | float) else value


def _check(
    bus: BusConfig | None, servos: ServoConfig | None, valve: ValveServoConfig | None,
    camera: CameraConfig | None, angle: AngleConfig | None, safety: SafetyConfig | None,
) -> list[str]:
    problems = []
    if servos is not None and valve is not None:
        problems += _check_servos(servos, valve)
    if bus is not None:
        if bus.baud not in BAUD_RATES:
            rates = ", ".join(map(str, BAUD_RATES))
            problems.append(f"bus.baud: {bus.baud} is not an XL-320 baud rate ({rates})")
        if not bus.port:
            problems.append("bus.port: must not be empty")
        if not 0 < bus.latency_ms <= 1000:
            problems.append(f"bus.latency_ms: must be in (0, 1000], got {bus.latency_ms}")
    if camera is not None:
        problems += _check_camera(camera)
    if angle is not None:
        problems += _check_angle(angle, valve)
    if safety is not None:
        problems += _check_safety(safety)
    if servos is not None and safety is not None and math.isfinite(servos.settle_s):
        # A step waits settle_s for its goals to act: longer than its timeout truncates every
        # step, and longer than the watchdog's hold has the watchdog hold the fingers mid-step.
        bound = min(safety.step_timeout_s, safety.watchdog_hold_s)
        if math.isfinite(bound) and bound > 0 and servos.settle_s >= bound:  # else blamed above
            problems.append(f"servos.settle_s: {servos.settle_s} must be below safety.step_timeout_s and "
                            f"safety.watchdog_hold_s ({bound})")
    return problems


def _check_camera(cam: CameraConfig) -> list[str]:
    problems = []
    for key in ("width", "height", "image_size"):
        if getattr(cam, key) < 1:
            problems.append(f"camera.{key}: must be >= 1, got {getattr(cam, key)}")
    if cam.index < 0:
        problems.append(f"camera.index: must be >= 0, got {cam.index}")
    if cam.drop_frames < 0:
        problems.append(f"camera.drop_frames: must be >= 0, got {cam.drop_frames}")
    if len(cam.valve_centre) != 2 or not all(0.0 <= v <= 1.0 for v in cam.valve_centre):
        problems.append(f"camera.valve_centre: must be [x, y] in 0..1, got {list(cam.valve_centre)}")
    if not 0.0 < cam.target_radius <= 1.0:
        problems.append(f"camera.target_radius: must be in (0, 1], got {cam.target_radius}")
    return problems


def _check_angle(a: AngleConfig, valve: ValveServoConfig | None) -> list[str]:
    problems = []
    if a.source not in ANGLE_SOURCES:
        problems.append(f"angle.source: {a.source!r} is not one of {', '.join(ANGLE_SOURCES)}")
    if a.source == "servo" and valve is not None and valve.id == 0:
        problems.append("angle.source: 'servo' needs a valve servo (valve.id is 0)")
    if a.direction not in (1, -1):
        problems.append(f"angle.direction: must be 1 or -1, got {a.direction}")
    if not math.isfinite(a.zero_deg):
        problems.append(f"angle.zero_deg: must be finite, got {a.zero_deg}")
    if a.aruco_dictionary not in ARUCO_DICTIONARIES:
        known = ", ".join(ARUCO_DICTIONARIES)
        problems.append(f"angle.aruco_dictionary: {a.aruco_dictionary!r} is not one of {known}")
    if a.aruco_id < 0:
        problems.append(f"angle.aruco_id: must be >= 0, got {a.aruco_id}")
    return problems


def _check_safety(s: SafetyConfig) -> list[str]:
    problems = []
    for key in ("step_timeout_s", "watchdog_hold_s", "watchdog_off_s", "home_timeout_s"):
        if not (math.isfinite(getattr(s, key)) and getattr(s, key) > 0):  # inf: an interlock off
            problems.append(f"safety.{key}: must be a finite number > 0, got {getattr(s, key)}")
    if s.watchdog_off_s < s.watchdog_hold_s:
        problems.append(
            f"safety.watchdog_off_s: {s.watchdog_off_s} is below safety.watchdog_hold_s ({s.watchdog_hold_s})"
        )
    if s.home_tolerance < 1:
        problems.append(f"safety.home_tolerance: must be >= 1, got {s.home_tolerance}")
    if not (math.isfinite(s.reboot_wait_s) and s.reboot_wait_s >= 0):
        problems.append(f"safety.reboot_wait_s: must be a finite number >= 0, got {s.reboot_wait_s}")
    return problems


def _check_servos(s: ServoConfig, v: ValveServoConfig) -> list[str]:
    problems = []
    for key in ("ids", "min_step", "max_step", "home"):
        if len(getattr(s, key)) != FINGER_SERVOS:
            problems.append(f"servos.{key}: must list {FINGER_SERVOS} values (one per finger servo), "
                            f"got {len(getattr(s, key))}")
    if problems:
        return problems
    for i, sid in enumerate(s.ids):
        if not 0 <= sid <= 252:
            problems.append(f"servos.ids[{i}]: {sid} is not a servo id (0..252)")
    if len(set(s.ids)) != len(s.ids):
        problems.append(f"servos.ids: ids must differ, got {list(s.ids)}")
    if v.id and v.id in s.ids:
        problems.append(f"valve.id: {v.id} is also a finger servo")
    if not 0 <= v.id <= 252:
        problems.append(f"valve.id: {v.id} is not a servo id (0..252, 0 for none)")
    for i, (lo, hi, home) in enumerate(zip(s.min_step, s.max_step, s.home, strict=True)):
        for key, value in (("min_step", lo), ("max_step", hi)):
            if not 0 <= value <= xl320.POSITION_MAX:
                problems.append(f"servos.{key}[{i}]: {value} is outside 0..{xl320.POSITION_MAX}")
        if lo >= hi:
            problems.append(f"servos.min_step[{i}]: {lo} is not below servos.max_step[{i}] ({hi})")
        elif not lo <= home <= hi:
            problems.append(f"servos.home[{i}]: {home} is outside servos.min_step..max_step ({lo}..{hi})")
    for name, value, top in (
        ("servos.moving_speed", s.moving_speed, xl320.SPEED_MAX),
        ("servos.torque_limit", s.torque_limit, xl320.TORQUE_MAX),
        ("valve.moving_speed", v.moving_speed, xl320.SPEED_MAX),
        ("valve.torque_limit", v.torque_limit, xl320.TORQUE_MAX),
    ):
        if not 1 <= value <= top:
            problems.append(f"{name}: {value} is outside 1..{top}")
    if s.max_step_change < 1:
        problems.append(f"servos.max_step_change: must be >= 1, got {s.max_step_change}")
    if not (math.isfinite(s.settle_s) and s.settle_s >= 0):
        problems.append(f"servos.settle_s: must be a finite number >= 0, got {s.settle_s}")
    return problems
