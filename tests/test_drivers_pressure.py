"""Pressure board driver over real pyserial on a real pty: protocol, garbage, timeouts, unplug."""

from __future__ import annotations

import fcntl
import os
import time
import tty

import numpy as np
import pytest

from collect.errors import HardwareFault, InputError
from collect.pressure_board import MAX_CORRUPT_RUN, MAX_FROZEN_RUN, PressureBoard, checksum, decode_line, encode_line
from conftest import wait_until


@pytest.fixture
def pty_board():
    """A ``PressureBoard`` on the slave of a fresh pty; the test plays the board on the master fd."""
    master, slave = os.openpty()
    tty.setraw(slave)
    fcntl.fcntl(master, fcntl.F_SETFL, fcntl.fcntl(master, fcntl.F_GETFL) | os.O_NONBLOCK)
    board = PressureBoard(os.ttyname(slave), stale_timeout_s=0.3)
    board.open()
    yield board, master
    board.close()
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def test_line_encoding_round_trip_and_checksum():
    line = encode_line("P,42,1065.31")
    assert line.endswith(b"\r\n")
    assert line == b"P,42,1065.31*" + checksum(b"P,42,1065.31").encode() + b"\r\n"
    assert decode_line(line.rstrip(b"\r\n")) == ["P", "42", "1065.31"]
    corrupted = line.replace(b"1065", b"1066").rstrip(b"\r\n")
    assert decode_line(corrupted) is None
    assert decode_line(b"P,42,1065.31") is None
    assert decode_line(b"\xff\xfe*00") is None
    assert decode_line(b"P,40,1065.31*7A") == ["P", "40", "1065.31"]
    assert decode_line(b"P,40,1065.31*7a") is None  # the protocol's hex is upper-case


@pytest.mark.parametrize("seq", ["01", "-5", "+5", "65536", "1_0"])
def test_a_reading_whose_sequence_number_the_protocol_never_writes_is_corrupt(pty_board, seq):
    board, master = pty_board
    os.write(master, encode_line("P,0,1065.00"))
    assert wait_until(lambda: board.latest() is not None)
    os.write(master, encode_line(f"P,{seq},1065.00"))
    assert wait_until(lambda: board.stats["malformed"] == 1)
    assert board.latest().seq == 0 and board.stats["readings"] == 1


def test_reader_survives_random_garbage_partial_lines_and_bad_checksums(pty_board, caplog):
    board, master = pty_board
    rng = np.random.default_rng(3)
    sent = 0
    for seq in range(200):
        if seq % 10 == 3:
            os.write(master, rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
        if seq % 10 == 5:
            os.write(master, b"P,999,1000.00*00\r\n")  # wrong checksum
        if seq % 10 == 7:
            os.write(master, encode_line(f"P,{seq},1.0")[:7])  # truncated, joins the next line
        if seq % 10 == 8:
            os.write(master, b"\n" + b"A" * 500 + b"\r\n")  # over-long line
        os.write(master, encode_line(f"P,{seq},{1060 + seq * 0.01:.2f}"))
        sent += 1
        time.sleep(0.0005)
    assert wait_until(lambda: board.latest() is not None and board.latest().seq == 199)
    readings = board.drain()
    board.check()  # no fault: garbage is recoverable
    good = [r for r in readings if r.hpa > 1000]
    # Lines right after random garbage or a truncated line may be eaten; every other one arrives intact.
    assert len(good) >= sent - 2 * 20 - 5
    assert all(r.hpa == pytest.approx(1060 + r.seq * 0.01) for r in good)
    assert board.stats["bad_checksum"] + board.stats["malformed"] >= 20
    assert board.stats["overlong"] >= 1
    assert [r.seq for r in good] == sorted(r.seq for r in good)
    assert "corrupt data" in caplog.text and "recovered" in caplog.text


def test_a_run_of_corrupt_lines_is_a_serial_garbage_fault(pty_board, caplog):
    board, master = pty_board
    os.write(master, encode_line("P,1,1060.00"))
    assert wait_until(lambda: board.latest() is not None)
    for _ in range(MAX_CORRUPT_RUN - 1):
        os.write(master, b"P,999,1000.00*00\r\n")
    os.write(master, encode_line("P,2,1060.00"))
    assert wait_until(lambda: board.latest().seq == 2)
    board.check()  # nine in a row: a glitch
    for _ in range(MAX_CORRUPT_RUN):
        os.write(master, b"P,999,1000.00*00\r\n")
    assert wait_until(lambda: board.stats["bad_checksum"] == 2 * MAX_CORRUPT_RUN - 1)
    caplog.clear()
    os.write(master, encode_line("P,3,1060.00"))  # good lines after the fault: it stays, said once
    assert wait_until(lambda: board.latest().seq == 3)
    with pytest.raises(HardwareFault) as err:
        board.check()
    assert err.value.kind == "serial-garbage"
    assert "recovered" not in caplog.text


def test_a_run_of_equal_readings_is_a_pressure_frozen_fault(pty_board):
    """Was: a board whose sensor stopped converting streamed its last value, and a leaking bubble
    passed the leak test on it (0 hPa/min)."""
    board, master = pty_board
    seq = 0

    def send(hpa: str, n: int) -> None:
        nonlocal seq
        for _ in range(n):
            os.write(master, encode_line(f"P,{seq},{hpa}"))
            seq += 1
            time.sleep(0.0005)
        assert wait_until(lambda: board.latest() is not None and board.latest().seq == seq - 1)

    send("1060.00", MAX_FROZEN_RUN - 1)
    send("1060.01", 1)  # one reading moved: the run starts again
    send("1060.01", MAX_FROZEN_RUN - 2)
    board.check()  # live: 99 equal readings in a row at most
    send("1060.01", 1)
    with pytest.raises(HardwareFault, match=r"pressure board: 100 readings in a row of 1060.01 hPa") as err:
        board.check()
    assert err.value.kind == "pressure-frozen"


def test_command_replies_errors_and_timeouts(pty_board):
    board, master = pty_board

    def answer(reply: bytes, expect: bytes):
        t_end = time.monotonic() + 2.0
        buf = b""
        while expect not in buf and time.monotonic() < t_end:
            try:
                buf += os.read(master, 64)
            except BlockingIOError:
                time.sleep(0.002)
        assert expect in buf
        os.write(master, encode_line("P,1,1000.00") + reply)

    import threading

    th = threading.Thread(target=answer, args=(encode_line("ID,BB-0042"), b"ID?\n"))
    th.start()
    assert board.identify() == "BB-0042"
    th.join()
    th = threading.Thread(target=answer, args=(encode_line("ID,BB 00/42"), b"ID?\n"))  # it names a folder
    th.start()
    with pytest.raises(HardwareFault, match="sensor serial 'BB 00/42' is not 1-64 letters") as err:
        board.identify()
    th.join()
    assert err.value.kind == "serial-protocol"
    th = threading.Thread(target=answer, args=(encode_line("ERR,unknown command LED 7"), b"LED 1\n"))
    th.start()
    with pytest.raises(HardwareFault) as err:
        board.set_led(True)
    th.join()
    assert err.value.kind == "serial-protocol"
    with pytest.raises(HardwareFault) as err:
        board.command("VER?", "VER", timeout_s=0.1)
    assert err.value.kind == "serial-timeout"


def test_a_board_that_stops_reading_its_port_times_a_command_out(pty_board):
    """Nobody reads the port (a hung board): the serial buffer fills and the command's write gives up
    after ``WRITE_TIMEOUT_S`` (was: no write timeout, the command waited forever)."""
    import threading

    from collect.pressure_board import WRITE_TIMEOUT_S

    board, _ = pty_board  # the test never reads the master: the board's side of the line stays full
    raised = []
    sender = threading.Thread(target=lambda: raised.append(pytest.raises(HardwareFault, board.command,
                                                                         "X" * 1_000_000, "X", timeout_s=0.1)),
                              daemon=True)
    sender.start()
    sender.join(WRITE_TIMEOUT_S + 5.0)
    assert not sender.is_alive(), "the command still waits to be sent"
    assert raised[0].value.kind == "serial-timeout" and "takes no data" in str(raised[0].value)


def test_silence_is_a_timeout_fault(pty_board):
    board, master = pty_board
    os.write(master, encode_line("P,0,1000.00"))
    assert wait_until(lambda: board.latest() is not None)
    board.check()
    time.sleep(0.4)
    with pytest.raises(HardwareFault) as err:
        board.check()
    assert err.value.kind == "serial-timeout"


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e999", "-3.00", "2500.00",
                                   # was read: what the protocol never writes (two equal bytes lost keep
                                   # the XOR: 1065.31 -> 065.31), and int()/float()'s other forms
                                   "065.31", "1_065.31", "1065.3", "+1065.31", "1e3", " 1065.31"])
def test_a_reading_outside_the_sensors_range_is_a_corrupt_line(pty_board, value):
    """Was: ``float()`` took ``nan``/``inf`` (what a driver prints for a failed conversion) as a valid
    reading: recorded, and a board whose sensor died streamed on without a fault."""
    board, master = pty_board
    os.write(master, encode_line("P,0,1065.00"))
    assert wait_until(lambda: board.latest() is not None)
    for seq in range(1, MAX_CORRUPT_RUN + 1):
        os.write(master, encode_line(f"P,{seq},{value}"))
    assert wait_until(lambda: board.stats["malformed"] == MAX_CORRUPT_RUN)
    assert board.latest().seq == 0 and board.stats["readings"] == 1
    with pytest.raises(HardwareFault) as err:
        board.check()
    assert err.value.kind == "serial-garbage"


def test_replies_without_readings_are_silence(pty_board):
    """Was: any valid line, an ``ERR`` reply included, kept the board fresh: a board that answered
    ``ERR,sensor not responding`` every half second never timed out."""
    board, master = pty_board
    os.write(master, encode_line("P,0,1065.00"))
    assert wait_until(lambda: board.latest() is not None)
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        os.write(master, encode_line("ERR,sensor not responding"))
        time.sleep(0.05)
    assert wait_until(lambda: board.stats["replies"] >= 5)
    with pytest.raises(HardwareFault) as err:
        board.check()
    assert err.value.kind == "serial-timeout"


def test_silence_counts_on_the_host_clock_too():
    """A bench clock that runs ahead (the simulated bench at --sim-speed N) while the reader thread
    is held back is not a silent board: the fault needs the timeout on both clocks (was: a false
    serial-timeout under load, one run in three of `bubble tui --sim --sim-speed 4`)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    bench_time = [100.0]
    board = PressureBoard(os.ttyname(slave), clock=lambda: bench_time[0], stale_timeout_s=0.3)
    board.open()
    try:
        os.write(master, encode_line("P,0,1000.00"))
        assert wait_until(lambda: board.latest() is not None)
        bench_time[0] += 5.0  # the simulated clock ran 5 s, the host's some milliseconds
        board.check()
        time.sleep(0.4)  # now both clocks passed the timeout in silence
        with pytest.raises(HardwareFault) as err:
            board.check()
        assert err.value.kind == "serial-timeout"
    finally:
        board.close()
        os.close(master)
        os.close(slave)


def test_unplug_is_detected(pty_board):
    board, master = pty_board
    board.stale_timeout_s = 60.0  # an unplug is its own fault, not a silence that lasted too long
    os.write(master, encode_line("P,0,1000.00"))
    assert wait_until(lambda: board.latest() is not None)
    os.close(master)
    t0 = time.monotonic()
    with pytest.raises(HardwareFault) as err:
        while time.monotonic() - t0 < 10.0:
            board.check()
            time.sleep(0.005)
    assert err.value.kind == "serial-unplug"


def test_a_port_open_in_another_run_is_refused(pty_board):
    """Two runs on one board would split its lines between them (each sees gaps and corrupt lines):
    the port is opened exclusively, and a second open is refused with one line until the first closes."""
    board, _ = pty_board
    second = PressureBoard(board.port)
    with pytest.raises(InputError, match=f"^pressure board: {board.port} is in use by another bubble process"):
        second.open()
    board.close()
    second.open()
    second.close()


def test_missing_port_is_a_fault():
    with pytest.raises(HardwareFault) as err:
        PressureBoard("/dev/does-not-exist-bubble").open()
    assert err.value.kind == "serial-missing"


def test_a_board_that_reboots_when_its_port_opens_is_waited_for(pty_board):
    """Opening the port raises DTR, which reboots boards wired like an Arduino: the first ``ID?``
    goes to the bootloader. Was: ``serial-timeout`` after 1 s (here: the 0.3 s stale limit too)."""
    import threading

    board, master = pty_board
    heard = []

    def boot_then_answer():
        booted_at = time.monotonic() + 1.2  # the bootloader: deaf and silent
        buf = b""
        while time.monotonic() < booted_at + 2.0:
            try:
                buf += os.read(master, 64)
            except BlockingIOError:
                time.sleep(0.002)
            if time.monotonic() < booted_at:
                heard.append(buf.count(b"ID?\n"))
                buf = b""
            elif b"ID?\n" in buf:
                os.write(master, encode_line("P,1,1000.00") + encode_line("ID,BB-0042"))
                return

    th = threading.Thread(target=boot_then_answer)
    th.start()
    assert board.identify() == "BB-0042"
    th.join()
    assert sum(heard) >= 2  # asked again while it booted
    board.check()
