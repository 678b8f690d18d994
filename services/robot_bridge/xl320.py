"""The Dynamixel XL-320's control table (Protocol 2.0) and units: the one place its addresses live."""

from __future__ import annotations

MODEL_NUMBER = 350

# address: (size in bytes, writable, initial value)
TORQUE_ENABLE = 24
LED = 25
GOAL_POSITION = 30
MOVING_SPEED = 32
TORQUE_LIMIT = 35
PRESENT_POSITION = 37
PRESENT_SPEED = 39
PRESENT_LOAD = 41
PRESENT_VOLTAGE = 45
PRESENT_TEMPERATURE = 46
MOVING = 49
HARDWARE_ERROR_STATUS = 50

# One sync-read block from present position to hardware error status covers everything a step
# checks (position, speed, load, voltage, temperature, moving, error bits) in one round trip.
STATE_BLOCK_START = PRESENT_POSITION
STATE_BLOCK_LENGTH = HARDWARE_ERROR_STATUS - PRESENT_POSITION + 1

# Hardware error status bits.
ERROR_OVERLOAD = 0x01
ERROR_OVERHEAT = 0x02
ERROR_VOLTAGE = 0x04
ERROR_NAMES = {ERROR_OVERLOAD: "overload", ERROR_OVERHEAT: "overheating", ERROR_VOLTAGE: "input voltage"}

POSITION_MAX = 1023
SPEED_MAX = 1023
TORQUE_MAX = 1023
LOAD_DIRECTION_BIT = 1024  # present load: 0..1023 one way, 1024..2047 the other

# (address, size, writable, initial) of every item, EEPROM then RAM.
CONTROL_TABLE: tuple[tuple[str, int, int, bool, int], ...] = (
    ("model_number", 0, 2, False, MODEL_NUMBER),
    ("firmware_version", 2, 1, False, 37),
    ("id", 3, 1, True, 1),
    ("baud_rate", 4, 1, True, 3),
    ("return_delay_time", 5, 1, True, 250),
    ("cw_angle_limit", 6, 2, True, 0),
    ("ccw_angle_limit", 8, 2, True, 1023),
    ("control_mode", 11, 1, True, 2),
    ("temperature_limit", 12, 1, True, 65),
    ("min_voltage_limit", 13, 1, True, 60),
    ("max_voltage_limit", 14, 1, True, 90),
    ("max_torque", 15, 2, True, 1023),
    ("status_return_level", 17, 1, True, 2),
    ("shutdown", 18, 1, True, 3),
    ("torque_enable", TORQUE_ENABLE, 1, True, 0),
    ("led", LED, 1, True, 0),
    ("d_gain", 27, 1, True, 0),
    ("i_gain", 28, 1, True, 0),
    ("p_gain", 29, 1, True, 32),
    ("goal_position", GOAL_POSITION, 2, True, 0),
    ("moving_speed", MOVING_SPEED, 2, True, 0),
    ("torque_limit", TORQUE_LIMIT, 2, True, 1023),
    ("present_position", PRESENT_POSITION, 2, False, 0),
    ("present_speed", PRESENT_SPEED, 2, False, 0),
    ("present_load", PRESENT_LOAD, 2, False, 0),
    ("present_voltage", PRESENT_VOLTAGE, 1, False, 74),
    ("present_temperature", PRESENT_TEMPERATURE, 1, False, 30),
    ("registered", 47, 1, False, 0),
    ("moving", MOVING, 1, False, 0),
    ("hardware_error_status", HARDWARE_ERROR_STATUS, 1, False, 0),
    ("punch", 51, 2, True, 32),
)
TABLE_SIZE = 53  # it ends there: no bus watchdog (an X-series servo's, at 98), the host must stop it
EEPROM_END = 24  # addresses below are EEPROM: writable only with torque off

# Units.
DEGREES_PER_STEP = 300.0 / 1024.0
RPM_PER_SPEED_UNIT = 0.111
NO_LOAD_RPM = 114.0


def steps_per_second(moving_speed: int) -> float:
    """How fast a servo moves toward its goal at a moving-speed setting (0: as fast as it can)."""
    rpm = NO_LOAD_RPM if moving_speed == 0 else min(moving_speed * RPM_PER_SPEED_UNIT, NO_LOAD_RPM)
    return rpm / 60.0 * 360.0 / DEGREES_PER_STEP


def error_names(bits: int) -> list[str]:
    return [name for bit, name in ERROR_NAMES.items() if bits & bit]


def signed_load(raw: int) -> int:
    """Present load as a signed value in -1023..1023 (about 0.1 % of the maximum torque per unit)."""
    magnitude = raw & 0x3FF
    return -magnitude if raw & LOAD_DIRECTION_BIT else magnitude
