"""Firmware emulator of the bubble pressure board, serving the line protocol on a pseudo-terminal.

``PressureFirmware(scene)`` opens a pty pair (``os.openpty``); ``.port`` is the slave path that
``collect.pressure_board.PressureBoard`` opens with pyserial, exactly as it opens
/dev/ttyACM0 for the real board. A thread plays the firmware on the master side: it streams
``P,<seq>,<hpa>*CS`` at ``rate_hz`` on the simulated clock and answers ``ID?``, ``VER?``,
``LED 0|1`` and ``STREAM 0|1`` (protocol in docs/hardware.md).

Readings: the scene's bubble pressure (``SimBench.pressure_hpa``: gas law of the membrane
solution, the leak of a leaky sensor included) plus the sensor's noise (``NOISE_HPA`` 1 sigma)
rounded to the 0.01 hPa resolution of the line.

Faults from the scene's schedule: ``serial-garbage`` replaces the stream with random bytes,
broken lines and bad checksums while active; ``serial-unplug`` closes the pty (the port vanishes);
``pressure-frozen`` repeats the last reading's pressure (a sensor that stopped converting).
Like a UART nobody listens to, output is dropped while the pty buffer is full.
"""

from __future__ import annotations

import fcntl
import os
import select
import tty

import numpy as np

from collect.loop_thread import LoopThread
from collect.pressure_board import SEQ_MODULO, encode_line

FIRMWARE_VERSION = "bubble-pb 1.3.0"
RATE_HZ = 100.0
NOISE_HPA = 0.03
#: The board's name in the bench's pacing (``SimBench.pace``): simulated time waits for a starved
#: emulator instead of running into a false ``serial-timeout``.
PACE_NAME = "pressure-board"


class PressureFirmware:
    """The emulated board of the scene's sensor (serial ``scene.spec.serial``)."""

    def __init__(self, scene, *, rate_hz: float = RATE_HZ, seed: int = 0):
        self.scene = scene
        self.rate_hz = rate_hz
        self.led = False  # the status LED (``LED 0|1``)
        self.streaming = True
        self._rng = np.random.default_rng(seed)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo / line editing before the driver configures the port
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.port = os.ttyname(self._slave)
        self._loop = LoopThread(self._run, "pressure-firmware", join_timeout_s=1.0)

    def start(self) -> None:
        """Start serving the port."""
        self._loop.start()

    def stop(self) -> None:
        """Stop serving and close both ends of the pty."""
        self._loop.stop()
        self._close()

    def _close(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def _write(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except BlockingIOError:
            pass  # nobody reads the port: the bytes are lost, as on a real UART

    def _garbage(self) -> bytes:
        """A burst of corruption: random bytes, a line with a wrong checksum, a truncated line."""
        noise = self._rng.integers(0, 256, size=int(self._rng.integers(1, 40)), dtype=np.uint8).tobytes()
        bad_cs = b"P,1,1013.25*00\r\n"
        truncated = encode_line(f"P,{int(self._rng.integers(SEQ_MODULO))},1013.25")[: int(self._rng.integers(2, 12))]
        return noise + bad_cs + truncated

    def _handle(self, command: str) -> None:
        words = command.strip().split()
        if not words:
            return
        if words == ["ID?"]:
            self._write(encode_line(f"ID,{self.scene.spec.serial}"))
        elif words == ["VER?"]:
            self._write(encode_line(f"VER,{FIRMWARE_VERSION}"))
        elif len(words) == 2 and words[0] in ("LED", "STREAM") and words[1] in ("0", "1"):
            setattr(self, "led" if words[0] == "LED" else "streaming", words[1] == "1")
            self._write(encode_line(f"OK,{' '.join(words)}"))
        else:
            self._write(encode_line(f"ERR,unknown command {' '.join(words)[:32]}"))

    def _run(self) -> None:
        try:
            self._serve()
        finally:
            self.scene.pace(PACE_NAME, None)

    def _serve(self) -> None:
        """The firmware's main loop: commands in, one reading line per period out."""
        clock = self.scene.clock
        period = 1.0 / self.rate_hz
        t_next = clock.now()
        seq = 0
        pending = b""
        hpa = None  # the last reading's pressure, hPa as printed
        while not self._loop.stop_event.is_set():
            if self.scene.fault_active("serial-unplug"):
                self._close()
                return
            readable, _, _ = select.select([self._master], [], [], 0)
            if readable:
                try:
                    pending += os.read(self._master, 256)
                except OSError:
                    pending = b""
                *lines, pending = pending.split(b"\n")
                pending = pending[-64:]
                for line in lines:
                    self._handle(line.decode("ascii", "replace"))
            if self.scene.fault_active("serial-garbage", t_next):
                self._write(self._garbage())
            elif self.streaming:
                if hpa is None or not self.scene.fault_active("pressure-frozen", t_next):
                    hpa = f"{self.scene.pressure_hpa(t_next) + NOISE_HPA * self._rng.standard_normal():.2f}"
                self._write(encode_line(f"P,{seq},{hpa}"))
            seq = (seq + 1) % SEQ_MODULO
            t_next += period
            self.scene.pace(PACE_NAME, t_next)
            if not clock.sleep_until(t_next, self._loop.stop_event):
                return
