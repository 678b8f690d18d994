"""The servo driver through the real dynamixel-sdk against the Protocol 2.0 emulator on a pty."""

import os
import random
import select
import termios
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from services.robot_bridge import protocol, xl320
from services.robot_bridge.dynamixel import BusError, ServoBus
from services.robot_bridge.emulator import BusEmulator

IDS = (1, 2, 3, 4)
# The emulator shares this machine with whatever else runs: a reply window (twice this) far wider
# than a USB adapter needs, so only an injected fault makes a reply late.
LATENCY_MS = 500.0


@pytest.fixture
def rig() -> Iterator[tuple[BusEmulator, ServoBus]]:
    with BusEmulator(IDS, positions={1: 300, 2: 400, 3: 500, 4: 600}) as emu:
        bus = ServoBus(emu.port, 1000000, IDS, latency_ms=LATENCY_MS)
        try:
            yield emu, bus
        finally:
            bus.close()


def wait_until(condition: Callable[[], bool], deadline_s: float = 10.0) -> None:
    """Poll until the condition holds; the deadline only stops a hung test."""
    end = time.monotonic() + deadline_s
    while not condition():
        assert time.monotonic() < end, "condition never held"
        time.sleep(0.02)


def test_framing_matches_a_known_packet() -> None:
    # The Protocol 2.0 manual's examples: a ping of id 1, and a read of 4 bytes at 132 from id 1.
    assert protocol.encode(1, protocol.PING).hex() == "fffffd0001030001194e"
    assert protocol.encode(1, protocol.READ, bytes((0x84, 0, 4, 0))).hex() == "fffffd0001070002840004001d15"
    stuffed = protocol.encode(1, protocol.WRITE, bytes((30, 0, 0xFF, 0xFF, 0xFD, 7)))
    assert b"\xff\xff\xfd\xfd" in stuffed[7:]
    packet = protocol.decode(bytearray(b"\x00noise" + stuffed))
    assert packet == protocol.Packet(1, protocol.WRITE, bytes((30, 0, 0xFF, 0xFF, 0xFD, 7)))


def test_sync_write_then_sync_read_round_trip(rig) -> None:
    emu, bus = rig
    assert all(bus.ping(sid) for sid in IDS)
    state = bus.read_state()
    assert list(state.position) == [300, 400, 500, 600]
    bus.set_torque(True)
    goals = {1: 310, 2: 390, 3: 512, 4: 1000}
    bus.write_goals(goals)
    assert [bus.read(sid, xl320.GOAL_POSITION, 2) for sid in IDS] == list(goals.values())
    assert [emu.snapshot(sid, xl320.GOAL_POSITION) for sid in IDS] == list(goals.values())


def test_positions_converge_at_the_moving_speed(rig) -> None:
    emu, bus = rig
    for sid in IDS:
        bus.set_limits(sid, moving_speed=100, torque_limit=500)
    assert emu.snapshot(1, xl320.TORQUE_LIMIT) == 500
    bus.set_torque(True)
    goals = {1: 700, 2: 100, 3: 500, 4: 650}
    bus.write_goals(goals)
    seen = []
    wait_until(lambda: seen.append(bus.read_state()) or list(seen[-1].position) == list(goals.values()))
    first, last = seen[0], seen[-1]
    assert first.moving[0] and not last.moving.any()
    assert first.load[0] > 0 > first.load[1]  # pushing toward the goal, each its own way
    # Monotonic travel toward the goal: a servo never overshoots.
    track = [s.position[0] for s in seen]
    assert track == sorted(track)


def test_error_bits_surface_and_reboot_clears_them(rig) -> None:
    emu, bus = rig
    bus.set_torque(True)
    emu.overload(2)
    state = bus.read_state()
    assert state.error[1] & xl320.ERROR_OVERLOAD
    assert state.faults(IDS) == {2: ["overload"]}
    assert bus.read(2, xl320.TORQUE_ENABLE, 1) == 0  # the servo's shutdown took torque off
    bus.reboot(2, wait_s=0.0)
    assert bus.hardware_error(2) == 0
    assert emu.servos[2].reboots == 1


def test_a_dead_servo_is_named(rig) -> None:
    emu, bus = rig
    emu.kill(3)
    with pytest.raises(BusError, match="not answering: \\[3\\]") as err:
        bus.read_state()
    assert err.value.servo_ids == (3,)
    with pytest.raises(BusError, match="servo 3"):
        bus.set_torque(True, ids=[3])
    emu.kill(3, dead=False)
    assert list(bus.read_state().position) == [300, 400, 500, 600]


def test_a_late_reply_times_out(rig) -> None:
    emu, bus = rig
    emu.delay(2, 2.5)
    with pytest.raises(BusError, match="no status packet|Incorrect status packet"):
        bus.read(2, xl320.PRESENT_POSITION, 2)
    emu.delay(2, 0.0)
    wait_until(lambda: bus.port.getBytesAvailable() > 0)  # the late reply, in the input
    # The next transfer clears it: of the same length, read as this answer it would say 400.
    assert bus.read(2, xl320.PRESENT_SPEED, 2) == 0
    assert bus.read(2, xl320.PRESENT_POSITION, 2) == 400


def test_waiting_for_a_late_reply_sleeps_on_the_port_instead_of_spinning(rig) -> None:
    emu, bus = rig
    reads: list[int] = []
    read_port = bus.port.readPort

    def counted(length: int) -> bytes:
        reads.append(length)
        return read_port(length)

    bus.port.readPort = counted
    delay_s = 0.4  # well inside the reply window (twice LATENCY_MS)
    emu.delay(2, delay_s)
    emu.delay(3, delay_s)
    cpu_start = time.thread_time()
    assert bus.read(2, xl320.PRESENT_POSITION, 2) == 400
    assert list(bus.read_state().position) == [300, 400, 500, 600]
    cpu_s = time.thread_time() - cpu_start
    # A polling loop reads the empty port thousands of times per delayed reply and burns the
    # whole delay in CPU; a wait on the port reads a few times per reply.
    assert len(reads) < 40, f"{len(reads)} reads of the port for 5 replies"
    assert cpu_s < 0.5 * (3 * delay_s), f"the waiting thread used {cpu_s:.3f} s of CPU"


def test_a_wall_clock_step_during_a_transfer_does_not_fail_it(rig, monkeypatch: pytest.MonkeyPatch) -> None:
    import dynamixel_sdk.port_handler as sdk_port

    class Stepping:  # the time module, but each read of the wall clock finds it an hour later
        def __init__(self) -> None:
            self.steps = 0

        def time(self) -> float:
            self.steps += 1
            return time.time() + 3600.0 * self.steps

        def __getattr__(self, name: str) -> object:
            return getattr(time, name)

    _, bus = rig
    monkeypatch.setattr(sdk_port, "time", Stepping())
    assert list(bus.read_state().position) == [300, 400, 500, 600]
    assert bus.read(2, xl320.PRESENT_POSITION, 2) == 400


def test_an_xl320_has_no_bus_watchdog_to_arm(rig) -> None:
    # 98 is an X-series servo's bus watchdog; the XL-320's table ends at 52: outside it, refused.
    _, bus = rig
    with pytest.raises(BusError, match="servo 1: write 5 at 98"):
        bus.write(1, 98, 5, 1)


def test_a_corrupt_crc_is_rejected(rig) -> None:
    emu, bus = rig
    emu.corrupt(1)
    with pytest.raises(BusError, match="Incorrect status packet"):
        bus.read_state()
    assert list(bus.read_state().position) == [300, 400, 500, 600]  # the next reply is clean


def test_the_emulator_answers_a_bad_instruction_crc_with_a_crc_error() -> None:
    with BusEmulator([7]) as emu:
        fd = os.open(emu.port, os.O_RDWR | os.O_NOCTTY)
        try:
            packet = bytearray(protocol.encode(7, protocol.PING))
            packet[-1] ^= 0xFF
            os.write(fd, bytes(packet))
            reply = bytearray()
            wait_until(lambda: reply.extend(os.read(fd, 64)) or protocol.HEADER in reply and len(reply) >= 11)
            status = protocol.decode(reply)
            assert status is not None and status.instruction == protocol.STATUS
            assert status.params[0] == protocol.ERR_CRC
        finally:
            os.close(fd)


def test_a_failing_serial_port_is_a_bus_error(rig) -> None:
    import serial

    emu, bus = rig
    real = bus.port.ser

    class Unplugged:  # what pyserial raises when the adapter goes away mid-transfer
        def __getattr__(self, name: str):  # noqa: ANN204
            return getattr(real, name)

        def write(self, data: bytes) -> int:
            raise serial.SerialException("write failed: [Errno 5] Input/output error")

        def read(self, size: int = 1) -> bytes:
            raise serial.SerialException("device reports readiness to read but returned no data")

    for call in (bus.read_state, lambda: bus.read(2, xl320.PRESENT_POSITION, 2),
                 lambda: bus.write_goals({1: 300}), lambda: bus.set_torque(False, [1]), lambda: bus.ping(1)):
        if not bus.port.is_open:  # the bus closed the failed port; open it as its next transfer would
            bus.port.openPort()
            real = bus.port.ser
        bus.port.ser = Unplugged()
        with pytest.raises(BusError, match="serial port"):
            call()
        assert not bus.port.is_open and not real.is_open
    assert list(bus.read_state().position) == [300, 400, 500, 600]  # opened anew


def status_reply(fd: int) -> protocol.Packet:
    """The next status packet the emulator writes on the bus (decoded with resynchronisation)."""
    reply = bytearray()
    got: list[protocol.Packet] = []

    def arrived() -> bool:
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            reply.extend(os.read(fd, 256))
        packet = protocol.decode(reply)
        return packet is not None and not got.append(packet)

    wait_until(arrived)
    return got[0]


@pytest.fixture
def raw_bus() -> Iterator[tuple[BusEmulator, int]]:
    with BusEmulator([7]) as emu:
        fd = os.open(emu.port, os.O_RDWR | os.O_NOCTTY)
        try:
            yield emu, fd
        finally:
            os.close(fd)


@pytest.mark.parametrize("noise", [
    protocol.HEADER + bytes((7, 0, 0)),  # a length too short for an instruction and a CRC
    protocol.HEADER + bytes((7, 2, 0, 0x01)),
    protocol.HEADER + bytes((7, 0xFF, 0xFF)),  # a length no packet has: would wait forever
    protocol.HEADER + bytes((7, 40, 0, 0x01)),  # a plausible length that swallows the real packet
    protocol.HEADER + bytes((7, 0x00, 0x02)),
    b"\xff\xff\xfd" + protocol.HEADER[:3],  # a header cut short by the next one
], ids=["length-0", "length-2", "length-65535", "length-40", "length-512", "cut-header"])
def test_the_emulator_resynchronises_after_a_noise_header(raw_bus, noise: bytes) -> None:
    emu, fd = raw_bus
    os.write(fd, noise + protocol.encode(7, protocol.PING))
    reply = status_reply(fd)
    assert (reply.servo_id, reply.instruction, reply.params[0]) == (7, protocol.STATUS, 0)
    assert int.from_bytes(reply.params[1:3], "little") == xl320.MODEL_NUMBER
    os.write(fd, protocol.encode(7, protocol.PING))  # and it goes on serving
    assert status_reply(fd).params[0] == 0


def test_the_emulator_answers_every_packet_among_random_noise(raw_bus) -> None:
    emu, fd = raw_bus
    rng = random.Random(3)
    for i in range(60):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40)))
        if rng.random() < 0.5:  # noise that starts like a packet, with any length
            junk = protocol.HEADER + bytes((rng.randrange(256), rng.randrange(256), rng.randrange(3))) + junk
        if rng.random() < 0.5:  # well-formed packets of any instruction and parameters, none for id 7
            params = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 12)))
            junk += protocol.encode(9, rng.randrange(256), params)
            junk += protocol.encode(protocol.BROADCAST_ID, protocol.SYNC_WRITE, params[:4] + b"\x09" + params)
        goal = (300 + i).to_bytes(2, "little")
        os.write(fd, junk + protocol.encode(7, protocol.WRITE, bytes((xl320.GOAL_POSITION, 0)) + goal))
        reply = status_reply(fd)
        assert (reply.servo_id, reply.params) == (7, b"\x00")
        assert emu.snapshot(7, xl320.GOAL_POSITION) == 300 + i


REPLY_NOISE = {
    "junk": bytes(range(0x10, 0x30)),
    "cut-header": protocol.HEADER[:3],
    "short-length": protocol.HEADER + bytes((2, 2, 0, 0x55)),  # a status header too short for a status
    "zero-length": protocol.HEADER + bytes((2, 0, 0, 0x55)),
    "long-length": protocol.HEADER + bytes((2, 0x00, 0x02, 0x55)),  # would swallow the replies after it
    "plausible-length": protocol.HEADER + bytes((2, 30, 0, 0x55)),
    "bad-crc": protocol.status(2, 0, b"\x01\x02")[:-1] + b"\x00",
}


@pytest.mark.parametrize("split", [False, True], ids=["whole", "split"])
@pytest.mark.parametrize("noise", list(REPLY_NOISE.values()), ids=list(REPLY_NOISE))
def test_the_driver_finds_a_reply_behind_line_noise(rig, noise: bytes, split: bool) -> None:
    emu, bus = rig
    emu.garble(2, noise, split)
    assert bus.read(2, xl320.PRESENT_POSITION, 2) == 400
    emu.garble(2, noise, split)  # between servo 1's reply and servo 2's in one sync read
    assert list(bus.read_state().position) == [300, 400, 500, 600]
    emu.garble(4, noise, split)  # after the last reply: nothing to find, nothing broken
    assert list(bus.read_state().position) == [300, 400, 500, 600]
    assert bus.ping(4)


def test_a_servo_that_refuses_a_sync_read_is_a_bus_error_naming_it(rig) -> None:
    emu, bus = rig
    emu.refuse(3, protocol.ERR_CRC)  # what it answers to a sync read that reached it corrupted
    with pytest.raises(BusError, match="servo 3.*CRC") as err:
        bus.read_state()
    assert err.value.servo_ids == (3,)
    emu.refuse(2, protocol.ERR_DATA_LENGTH)
    with pytest.raises(BusError, match="servo 2"):
        bus.read(2, xl320.PRESENT_POSITION, 2)
    assert list(bus.read_state().position) == [300, 400, 500, 600]


def test_a_babbling_bus_times_out_instead_of_hanging(rig) -> None:
    emu, bus = rig
    babbling = threading.Event()
    stop = threading.Event()

    def babble() -> None:  # a device on the line that never stops sending noise (no header in it)
        end = time.monotonic() + 60.0
        while not stop.is_set() and time.monotonic() < end:
            babbling.set()
            try:
                os.write(emu._master, bytes(range(0x10, 0x30)))
            except BlockingIOError:  # the pty is full: nobody reads just now
                time.sleep(0.01)
        babbling.clear()

    emu.kill(2)
    os.set_blocking(emu._master, False)  # nothing else writes: servo 2 is dead
    thread = threading.Thread(target=babble, daemon=True)
    thread.start()
    try:
        babbling.wait()
        with pytest.raises(BusError, match="servo 2"):
            bus.read(2, xl320.PRESENT_POSITION, 2)
        assert babbling.is_set()  # it gave up by its own timeout, not because the noise stopped
    finally:
        stop.set()
        thread.join()
        os.set_blocking(emu._master, True)


def test_a_late_answer_to_another_instruction_is_not_taken_for_the_reply(rig) -> None:
    emu, bus = rig
    late_ping = protocol.status(2, 0, xl320.MODEL_NUMBER.to_bytes(2, "little") + b"\x25")
    emu.garble(2, late_ping)  # on the line before the read's own reply
    assert bus.read(2, xl320.PRESENT_POSITION, 2) == 400  # not the model number, 350
    emu.garble(2, protocol.status(2, 0))  # a write's bare status before the sync read's reply
    assert list(bus.read_state().position) == [300, 400, 500, 600]


def test_an_adapter_unplugged_and_plugged_back_is_reopened(tmp_path) -> None:
    link = tmp_path / "ttyDXL"  # the stable name udev gives the adapter, as /dev/serial/by-id does
    first = BusEmulator(IDS, positions={1: 300, 2: 400, 3: 500, 4: 600}).__enter__()
    link.symlink_to(first.port)
    bus = ServoBus(str(link), 1000000, IDS, latency_ms=LATENCY_MS)
    try:
        assert list(bus.read_state().position) == [300, 400, 500, 600]
        first.close()  # unplugged: the pty is gone, the bus's file is dead
        with pytest.raises(BusError, match="serial port"):
            bus.read_state()
        with pytest.raises(BusError) as missing:  # the reopen finds no device under the name
            bus.read_state()
        assert str(missing.value) == f"serial port {link}: No such file or directory"
        with BusEmulator(IDS, positions={1: 310, 2: 410, 3: 510, 4: 610}) as second:  # plugged back
            link.unlink()
            link.symlink_to(second.port)
            assert list(bus.read_state().position) == [310, 410, 510, 610]
    finally:
        bus.close()
        first.close()
    with pytest.raises(BusError, match="closed"):
        bus.read_state()  # a bus closed on purpose stays closed


def test_a_missing_adapter_is_named_once_with_the_systems_reason(tmp_path) -> None:
    missing = tmp_path / "ttyUSB9"
    with pytest.raises(BusError) as refused:
        ServoBus(str(missing), 1000000, IDS, latency_ms=LATENCY_MS)
    assert str(refused.value) == f"cannot open {missing}: No such file or directory"


def test_a_second_opener_of_a_held_port_is_refused_and_the_first_runs_on(rig) -> None:
    """Two programs on one bus would interleave their packets: the second is refused, one line
    naming the port and the process that holds it, before it sends a byte or changes a setting."""
    emu, bus = rig
    settings = termios.tcgetattr(bus.port.ser.fileno())
    seen = emu.packets_seen
    for baud in (1000000, 57600):  # the same rate, and another one, which would change the port's
        with pytest.raises(BusError) as refused:
            ServoBus(emu.port, baud, IDS, latency_ms=LATENCY_MS)
        message = str(refused.value)
        assert message.startswith(f"cannot open {emu.port}: in use by another") and "\n" not in message
        assert f"pid {os.getpid()}: " in message, message
    assert emu.packets_seen == seen
    assert termios.tcgetattr(bus.port.ser.fileno()) == settings
    bus.write_goals({1: 310, 2: 410, 3: 510, 4: 610})
    assert list(bus.read_state().position) == [300, 400, 500, 600]  # torque off: goals set, nothing moves
    assert [bus.read(sid, xl320.GOAL_POSITION, 2) for sid in IDS] == [310, 410, 510, 610]
    bus.close()  # let go: the port is free for the next opener
    ServoBus(emu.port, 1000000, IDS, latency_ms=LATENCY_MS).close()
