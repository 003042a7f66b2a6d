"""Bubble pressure board: line protocol over USB serial (pyserial), 115200 baud, ~100 Hz.

Protocol (full description in docs/hardware.md). Every board line is ASCII,
``<body>*<CS>\\r\\n``, where CS is two upper-case hex digits of the XOR of the body's bytes:

* ``P,<seq>,<hpa>``   reading: seq 0..65535 (wraps), absolute pressure in hPa, streamed at 100 Hz
* ``ID,<serial>``     reply to ``ID?`` (the serial of the bubble sensor the board lives in)
* ``VER,<version>``   reply to ``VER?``
* ``OK,<command>``    reply to an accepted ``LED 0|1`` / ``STREAM 0|1``
* ``ERR,<reason>``    reply to a bad command

Host commands are plain ASCII lines ending in ``\\n``: ``ID?``, ``VER?``, ``LED 0|1``, ``STREAM 0|1``.

``PressureBoard`` reads in a background thread. Garbage bytes, partial or over-long lines and
bad checksums are counted (``stats``) and skipped, and logged once per burst with a recovery
line: a glitch (the partial line read on opening, a few corrupt lines) is survived.
``check()`` raises ``HardwareFault('serial-garbage')`` once ``MAX_CORRUPT_RUN`` corrupt lines came
in a row (a tenth of a second of the stream: noise on the cable, a wrong baud rate),
``HardwareFault('serial-unplug')`` once the port vanished (read error), and
``HardwareFault('serial-timeout')`` when no valid reading (a ``P`` line with a pressure within
``HPA_RANGE``; replies such as ``ERR`` do not count) came for ``stale_timeout_s``, both on
the bench clock and on the host's (the same clock on real hardware; on the simulated bench, whose
clock runs ``--sim-speed`` times faster, a reader thread the OS holds back for a quarter of a
second is not a silent board). ``HardwareFault('pressure-frozen')`` is a board that streams
``MAX_FROZEN_RUN`` readings in a row of exactly the same pressure: a sensor that stopped converting,
whose firmware repeats its last value (a live sensor's noise moves the line's last digit; a frozen
one would pass the leak test of a leaking bubble).
"""

from __future__ import annotations

import errno
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from collect.errors import HardwareFault, InputError
from collect.loop_thread import LoopThread

log = logging.getLogger(__name__)

BAUDRATE = 115200
MAX_LINE_BYTES = 96
SEQ_MODULO = 65536
STALE_TIMEOUT_S = 1.0
#: A sensor serial: the board's answer to ``ID?``, the sensor's registry folder name; it fits a line.
SENSOR_SERIAL_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
SENSOR_SERIAL_RULE = "1-64 letters, digits, '.', '_' or '-', the first a letter or digit"
#: Corrupt lines in a row that make a ``serial-garbage`` fault (0.1 s of the 100 Hz stream).
MAX_CORRUPT_RUN = 10
#: Longest time (s) a command may wait to be sent: a board that stops reading its port fills the
#: serial buffer, and a write would then wait for it forever.
WRITE_TIMEOUT_S = 1.0
#: s a board may stay silent after its port opens: opening raises DTR, which reboots boards wired
#: like an Arduino (a bootloader waits 1-2 s); ``ID?`` is repeated every ``BOOT_RETRY_S`` until
#: then, and silence is no ``serial-timeout`` before the board's first valid line or this long.
BOOT_WAIT_S = 3.0
BOOT_RETRY_S = 0.5
#: hPa a reading may hold: the board's MPRLS-class sensor spans 0-25 psi (0-1724 hPa absolute). A
#: value outside (a ``nan`` or ``inf`` a driver prints for a failed conversion) is a corrupt line.
HPA_RANGE = (0.0, 1724.0)
#: Readings in a row of exactly the same pressure that make a ``pressure-frozen`` fault: 1 s of the
#: 100 Hz stream. The sensor's noise (about 0.03 hPa, twice the line's 0.01 hPa resolution) changes
#: nine in ten live readings; a hundred equal ones in a row never come from a converting sensor.
MAX_FROZEN_RUN = 100


#: The fields of a reading line as the protocol writes them: ``seq`` without leading zeros, and hPa
#: with two decimals. A line that XOR checks but reads otherwise is corrupt: two equal bytes lost
#: keep the checksum (``P,1234,1065.31`` -> ``P,234,065.31``, 65.31 hPa), and ``int``/``float``
#: alone took signs, ``_`` and exponents (was: such readings went into the stream and the leak test).
READING_FIELDS = re.compile(r"(0|[1-9][0-9]{0,4}),(0|[1-9][0-9]{0,3})\.[0-9]{2}")


def checksum(body: bytes) -> str:
    """Two-hex-digit XOR checksum of ``body``."""
    value = 0
    for byte in body:
        value ^= byte
    return f"{value:02X}"


def encode_line(body: str) -> bytes:
    """A board line ``<body>*<CS>\\r\\n`` as bytes."""
    raw = body.encode("ascii")
    return raw + b"*" + checksum(raw).encode("ascii") + b"\r\n"


def decode_line(line: bytes) -> list[str] | None:
    """Fields of one board line (without its line end), or None when malformed or the checksum is wrong."""
    body, star, cs = line.rpartition(b"*")
    if not star or len(cs) != 2:
        return None
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        return None
    if not text.isprintable() or cs.decode("ascii", "replace") != checksum(body):  # upper-case hex, as written
        return None
    return text.split(",")


@dataclass(frozen=True)
class PressureReading:
    """One reading: ``t`` s on the bench clock (host receive time), board ``seq``, ``hpa`` absolute pressure."""

    t: float
    seq: int
    hpa: float


class PressureBoard:
    """Driver of the pressure board on ``port`` (a device path, e.g. /dev/ttyACM0 or a pty slave)."""

    def __init__(self, port: str, *, clock: Callable[[], float] = time.monotonic,
                 stale_timeout_s: float = STALE_TIMEOUT_S, baudrate: int = BAUDRATE):
        self.port = port
        self.baudrate = baudrate
        self.stale_timeout_s = stale_timeout_s
        self._clock = clock
        self._serial: serial.Serial | None = None
        self._reader_loop = LoopThread(self._reader, "pressure-reader", join_timeout_s=1.0)
        self._lock = threading.Condition()
        self._latest: PressureReading | None = None
        self._readings: list[PressureReading] = []
        self._replies: list[list[str]] = []
        self._fault: HardwareFault | None = None
        self._last_valid = 0.0  # bench clock, s
        self._last_valid_host = 0.0  # time.monotonic(), s
        self._bad_run = 0
        self._same_run = 0  # readings in a row equal to the latest (``pressure-frozen`` after MAX_FROZEN_RUN)
        self._heard = False  # a valid line came since the port opened
        self._boot_deadline = 0.0  # time.monotonic() until which silence is a board booting
        self.stats = {"readings": 0, "replies": 0, "bad_checksum": 0, "malformed": 0, "overlong": 0, "seq_gaps": 0}

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the port and start the reader thread."""
        try:  # exclusive: flock(2) on the port, so that two runs never split the board's lines between them
            self._serial = serial.Serial(self.port, self.baudrate, timeout=0.05, write_timeout=WRITE_TIMEOUT_S,
                                         exclusive=True)
        except (serial.SerialException, OSError) as err:
            if err.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise InputError(f"pressure board: {self.port} is in use by another bubble process; wait until "
                                 "it has finished, or check serial_port") from err
            raise HardwareFault("serial-missing", f"pressure board: cannot open {self.port}: {err}") from err
        self._serial.reset_input_buffer()
        self._last_valid, self._last_valid_host = self._clock(), time.monotonic()
        self._boot_deadline = time.monotonic() + BOOT_WAIT_S
        self._reader_loop.start()

    def close(self) -> None:
        """Stop the reader and close the port."""
        self._reader_loop.stop()
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    # ------------------------------------------------------------------ reader thread
    def _reader(self) -> None:
        buffer = b""
        while not self._reader_loop.stop_event.is_set():
            try:
                chunk = self._serial.read(max(1, self._serial.in_waiting))
            except (serial.SerialException, OSError, TypeError) as err:
                self._set_fault(HardwareFault("serial-unplug", f"pressure board: {self.port} vanished ({err})"))
                return
            if not chunk:
                continue
            t = self._clock()
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            if len(buffer) > MAX_LINE_BYTES:
                self.stats["overlong"] += 1
                self._bad()
                buffer = b""
            for line in lines:
                self._handle(line.rstrip(b"\r"), t)

    def _handle(self, line: bytes, t: float) -> None:
        if not line:
            return
        if len(line) > MAX_LINE_BYTES:
            self.stats["overlong"] += 1
            self._bad()
            return
        fields = decode_line(line)
        if fields is None:
            self.stats["bad_checksum" if b"*" in line and line.isascii() else "malformed"] += 1
            self._bad()
            return
        if fields[0] == "P" and len(fields) == 3:
            if READING_FIELDS.fullmatch(f"{fields[1]},{fields[2]}"):
                seq, hpa = int(fields[1]), float(fields[2])
            else:
                seq, hpa = None, None
            if seq is None or seq >= SEQ_MODULO or not HPA_RANGE[0] <= hpa <= HPA_RANGE[1]:
                self.stats["malformed"] += 1
                self._bad()
                return
            self._good(reading=True)
            with self._lock:
                if self._latest is not None:
                    self.stats["seq_gaps"] += (seq - self._latest.seq - 1) % SEQ_MODULO
                self._same_run = self._same_run + 1 if self._latest is not None and hpa == self._latest.hpa else 1
                reading = PressureReading(t, seq, hpa)
                self._latest = reading
                self._readings.append(reading)
                self.stats["readings"] += 1
                self._lock.notify_all()
            if self._same_run == MAX_FROZEN_RUN:
                self._set_fault(HardwareFault(
                    "pressure-frozen", f"pressure board: {MAX_FROZEN_RUN} readings in a row of {hpa:.2f} hPa on "
                                       f"{self.port} (its sensor stopped converting; power-cycle the board)"))
        elif fields[0] in ("ID", "VER", "OK", "ERR"):
            self._good(reading=False)
            with self._lock:
                self._replies.append(fields)
                self.stats["replies"] += 1
                self._lock.notify_all()
        else:
            self.stats["malformed"] += 1
            self._bad()

    def _bad(self) -> None:
        if self._bad_run == 0:
            log.warning("pressure board: corrupt data on %s, skipping", self.port)
        self._bad_run += 1
        if self._bad_run == MAX_CORRUPT_RUN:
            self._set_fault(HardwareFault(
                "serial-garbage", f"pressure board: {MAX_CORRUPT_RUN} corrupt lines in a row on {self.port} "
                                  f"(noise on the cable or a wrong baud rate)"))

    def _good(self, reading: bool) -> None:
        """A valid line came: it ends a run of corrupt ones. A ``reading`` keeps the stream fresh, and so
        does the board's first line (its silence before was a boot); a reply alone later does not."""
        if reading or not self._heard:
            self._last_valid, self._last_valid_host = self._clock(), time.monotonic()
        self._heard = True
        if self._bad_run:
            if self._fault is None:  # after a serial-garbage fault the run is over: no "recovered"
                log.warning("pressure board: recovered after %d corrupt lines", self._bad_run)
            self._bad_run = 0

    def _set_fault(self, fault: HardwareFault) -> None:
        with self._lock:
            if self._fault is None:
                self._fault = fault
            self._lock.notify_all()

    # ------------------------------------------------------------------ API
    def check(self) -> None:
        """Raise the fault of the board: a run of corrupt lines, unplugged, or no valid reading for
        ``stale_timeout_s`` on the bench clock and on the host's (once the board has spoken, or
        ``BOOT_WAIT_S`` after the port opened: a board rebooting on the open is silent till then)."""
        if (self._fault is None and self._reader_loop.running
                and (self._heard or time.monotonic() > self._boot_deadline)
                and self._clock() - self._last_valid > self.stale_timeout_s
                and time.monotonic() - self._last_valid_host > self.stale_timeout_s):
            self._set_fault(HardwareFault(
                "serial-timeout", f"pressure board: no valid reading for {self.stale_timeout_s:.1f} s on {self.port}"))
        if self._fault is not None:
            raise self._fault

    def latest(self) -> PressureReading | None:
        """Most recent reading, or None before the first one."""
        with self._lock:
            return self._latest

    def drain(self) -> list[PressureReading]:
        """Every reading since the previous call (the pressure stream for the recorder)."""
        with self._lock:
            out, self._readings = self._readings, []
        return out

    def wait_reading(self, timeout_s: float = 1.0) -> PressureReading:
        """Block until a new reading arrives; raises the board's fault or ``serial-timeout``."""
        with self._lock:
            seen = self._latest
            self._lock.wait_for(lambda: self._latest is not seen or self._fault is not None, timeout=timeout_s)
            fresh = self._latest is not seen
        self.check()
        if not fresh:
            raise HardwareFault("serial-timeout", f"pressure board: no reading within {timeout_s:.1f} s")
        return self._latest

    def command(self, text: str, reply: str, timeout_s: float = 1.0) -> list[str]:
        """Send one command line and return the fields of its reply (first field ``reply`` or ``ERR``)."""
        self.check()
        with self._lock:
            self._replies.clear()
        try:
            self._serial.write(text.encode("ascii") + b"\n")
        except serial.SerialTimeoutException as err:  # was: no write timeout, and the command waited forever
            raise HardwareFault("serial-timeout", f"pressure board: {self.port} takes no data: '{text[:20]}' waited "
                                                  f"{WRITE_TIMEOUT_S:g} s to be sent (board hung?)") from err
        except (serial.SerialException, OSError) as err:
            self._set_fault(HardwareFault("serial-unplug", f"pressure board: {self.port} vanished ({err})"))
            raise self._fault from err
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                for fields in self._replies:
                    if fields[0] in (reply, "ERR"):
                        self._replies.remove(fields)
                        if fields[0] == "ERR":
                            raise HardwareFault("serial-protocol", f"pressure board: '{text}' failed: {','.join(fields[1:])}")
                        return fields
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._fault is not None:
                    break
                self._lock.wait(remaining)
        self.check()
        raise HardwareFault("serial-timeout", f"pressure board: no reply to '{text}' within {timeout_s:.1f} s")

    def identify(self) -> str:
        """Serial number of the bubble sensor the board is built into (``ID?``); a serial that breaks
        ``SENSOR_SERIAL_RULE`` (a badly flashed board) raises ``HardwareFault('serial-protocol')``.
        Until ``BOOT_WAIT_S`` after the port opened, an unanswered ``ID?`` is sent again every
        ``BOOT_RETRY_S`` (a board that reboots on the open misses the first; was: ``serial-timeout``)."""
        while True:
            booting = time.monotonic() < self._boot_deadline
            try:
                fields = self.command("ID?", "ID", timeout_s=BOOT_RETRY_S if booting else 1.0)
                break
            except HardwareFault as fault:
                if fault.kind != "serial-timeout" or not booting:
                    raise
        serial_number = ",".join(fields[1:])
        if not SENSOR_SERIAL_RE.fullmatch(serial_number):
            raise HardwareFault("serial-protocol", f"pressure board: its sensor serial {serial_number!r} is not "
                                                   f"{SENSOR_SERIAL_RULE}; flash a valid one")
        return serial_number

    def firmware_version(self) -> str:
        """Firmware version string (``VER?``)."""
        return ",".join(self.command("VER?", "VER")[1:])

    def set_led(self, on: bool) -> None:
        """Switch the board's status LED (``LED 0|1``)."""
        self.command(f"LED {int(bool(on))}", "OK")
