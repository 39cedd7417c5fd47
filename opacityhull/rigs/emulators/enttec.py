"""Enttec DMX USB Pro emulator: keeps the DMX universe the host sends, answers labels 3/10.

Behaviour follows the widget API 1.44: label 6 packets whose start code is 0 set the
output universe (data length 25..513 bytes: shorter packets are ignored and flagged;
channels beyond the packet length are not transmitted, so they read 0); a packet with
another start code (RDM, text) is counted and does not change the levels; label 3 is
answered with the firmware version, break/MAB times and output rate; label 4 sets them;
label 10 is answered with the serial number (BCD). Unknown labels are ignored (and
listed in :attr:`EnttecEmulator.ignored`), malformed frames are skipped by the same
re-synchronising :class:`~opacityhull.rigs.enttec_protocol.FrameParser` the driver uses
and listed in :attr:`EnttecEmulator.bad_frames`. With ``faults.silent`` set the widget
is hung: it neither answers nor updates its output.
"""

from __future__ import annotations

import logging

from .. import enttec_protocol as ep
from .base import EmulatedDevice, Reply

log = logging.getLogger(__name__)

__all__ = ["EnttecEmulator"]


class EnttecEmulator(EmulatedDevice):
    """An Enttec DMX USB Pro widget.

    Parameters
    ----------
    universe_size : channels in the output universe (24..512).
    serial : serial number as BCD digits, e.g. 0x12345678 prints as "12345678".
    firmware : (major, minor) firmware version; major 1 = normal DMX firmware.
    """

    name = "enttec"

    def __init__(
        self,
        *,
        universe_size: int = 512,
        serial: int = 0x12345678,
        firmware: tuple[int, int] = (1, 44),
        time_scale: float = 0.0,
    ):
        super().__init__(time_scale=time_scale)
        if not ep.MIN_DMX_CHANNELS <= int(universe_size) <= ep.DMX_CHANNELS:
            raise ValueError(f"universe_size must be {ep.MIN_DMX_CHANNELS}..{ep.DMX_CHANNELS}, got {universe_size}")
        self.universe_size = int(universe_size)
        self.serial = int(serial)
        self.params = ep.WidgetParameters(
            firmware=(int(firmware[0]), int(firmware[1])), break_time=9, mab_time=1, rate_hz=40
        )
        self._levels = bytearray(self.universe_size)
        self._parser = ep.FrameParser()
        self.frames_received = 0  # well-formed frames of any label
        self.dmx_packets = 0  # label-6 packets applied to the output
        self.other_start_codes: list[int] = []
        self.ignored: list[ep.Frame] = []
        self._flagged: list[tuple[str, ep.Frame]] = []  # well-formed frames with invalid content
        self.history: list[bytes] = []  # every universe applied, oldest first (bounded)
        self._history_max = 10000

    # ------------------------------------------------------------------ public state
    def levels(self) -> bytes:
        """The output universe now: ``universe_size`` bytes, channel 1 at index 0."""
        with self.lock:
            return bytes(self._levels)

    def level(self, channel: int) -> int:
        """Level of one 1-based DMX channel."""
        with self.lock:
            return self._levels[channel - 1]

    @property
    def bad_frames(self) -> list:
        """Malformed input as :class:`~opacityhull.rigs.enttec_protocol.BadFrame` (reason, bytes)."""
        with self.lock:
            return list(self._parser.bad) + [ep.BadFrame(why, f.data) for why, f in self._flagged]

    # ------------------------------------------------------------------ bytes in
    def receive(self, data: bytes):
        if self.faults.silent:
            return []  # hung widget: no output update, no replies
        out: list[Reply] = []
        for f in self._parser.feed(data):
            self.frames_received += 1
            out += self._handle(f)
        return out

    def _handle(self, f: ep.Frame) -> list[Reply]:
        if f.label == ep.LABEL_SEND_DMX:
            if not f.data:
                self._flag("empty DMX packet", f)
                return []
            start, levels = f.data[0], f.data[1:]
            if len(levels) < ep.MIN_DMX_CHANNELS:
                self._flag(f"DMX packet of {len(levels)} channels < {ep.MIN_DMX_CHANNELS}", f)
                return []
            if start != 0:
                self.other_start_codes.append(start)
                return []
            n = min(len(levels), self.universe_size)
            self._levels[:n] = levels[:n]
            self._levels[n:] = bytes(self.universe_size - n)
            self.dmx_packets += 1
            if len(self.history) < self._history_max:
                self.history.append(bytes(self._levels))
            return []
        if f.label == ep.LABEL_GET_PARAMS:
            if len(f.data) != 2:
                self._flag("Get Widget Parameters request must carry 2 bytes", f)
                return []
            size = min(f.data[0] | (f.data[1] << 8), 508)
            p = self.params
            reply = ep.WidgetParameters(p.firmware, p.break_time, p.mab_time, p.rate_hz, bytes(size))
            return [Reply(ep.encode_widget_parameters_reply(reply))]
        if f.label == ep.LABEL_SET_PARAMS:
            if len(f.data) < 5:
                self._flag("Set Widget Parameters needs 5 bytes", f)
                return []
            d = f.data
            self.params = ep.WidgetParameters(self.params.firmware, d[2], d[3], d[4])
            return []
        if f.label == ep.LABEL_GET_SERIAL:
            return [Reply(ep.encode_serial_reply(self.serial))]
        self.ignored.append(f)
        return []

    def _flag(self, why: str, f: ep.Frame) -> None:
        self._flagged.append((why, f))
