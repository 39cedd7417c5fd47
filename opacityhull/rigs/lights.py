"""Light-array drivers: the Enttec DMX USB Pro widget and the array of lights behind it.

DMX512 is send-only: the widget never acknowledges a packet, and it keeps repeating the
last universe on the DMX line by itself. So a dead widget is noticed three ways here:
a write fails (pty hang-up, USB gone: :class:`~opacityhull.rigs.transport.DeviceGone`);
before each write the port is polled, which exposes a closed TCP peer that a write would
not report yet; and :meth:`EnttecDmx.check` / :meth:`DmxLightArray.check` ask the widget
for its parameters and serial number (labels 3 and 10), which only a live widget answers.
:meth:`EnttecDmx.start_keepalive` re-sends the universe periodically in the background
and remembers the first failure, which the next :meth:`~EnttecDmx.send_dmx` raises.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping

from ..errors import ConfigError, DeviceError, InputError
from ..interrupts import signals_off_this_thread
from . import enttec_protocol as ep
from .interfaces import DeviceInfo, RotaryAxis, check_opened
from .transport import DeviceGone, DeviceTimeout, OverTransport, SerialSettings, SerialTransport, Transport, driver_name

log = logging.getLogger(__name__)

__all__ = ["DMX_SERIAL", "EnttecDmx", "DmxLightArray"]

#: The widget's virtual COM port ignores the baud rate (57600 by convention). DMX is never
#: acknowledged and the rig re-opens a vanished widget: ``retries`` and ``reconnect_*`` are unused.
DMX_SERIAL = SerialSettings(baudrate=57600, timeout_s=2.0, retries=0, reconnect_attempts=0, reconnect_delay_s=0.0)


def _check_universe_size(name: str, universe_size: int) -> None:
    if (
        isinstance(universe_size, bool)
        or not isinstance(universe_size, int)
        or not ep.MIN_DMX_CHANNELS <= universe_size <= ep.DMX_CHANNELS
    ):
        raise ConfigError(
            f"{name}: universe_size = {universe_size!r}, expected an integer {ep.MIN_DMX_CHANNELS}..{ep.DMX_CHANNELS}"
        )


class EnttecDmx(OverTransport):
    """Driver of one Enttec DMX USB Pro (one DMX universe).

    Parameters
    ----------
    transport : the byte transport (:meth:`from_url` builds a serial one on the widget's
        virtual COM port; its baud rate is a dummy value).
    name : device name in messages (default: the transport's).
    serial : :class:`~opacityhull.rigs.transport.SerialSettings` (default :data:`DMX_SERIAL`):
        ``timeout_s`` per reply (labels 3, 10); ``baudrate`` is the transport's.
    universe_size : channels sent in every packet (24..512); unused channels are 0.
    verify_on_open : :meth:`open` asks for the widget parameters, so a wrong port or an
        Open DMX (no processor, never answers) fails at once.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        name: str | None = None,
        serial: SerialSettings = DMX_SERIAL,
        universe_size: int = 512,
        verify_on_open: bool = True,
    ):
        name = driver_name(transport, name, driver="EnttecDmx", fallback="dmx")
        _check_universe_size(name, universe_size)
        self.name = name
        self.timeout_s = float(serial.timeout_s)
        self.universe_size = universe_size
        self.verify_on_open = verify_on_open
        self.transport = transport
        self.lock = threading.RLock()
        self._parser = ep.FrameParser()
        self._last: bytes | None = None
        self.packets_sent = 0
        self.unsolicited: list[ep.Frame] = []  # frames nobody asked for (bounded)
        self._keepalive: threading.Thread | None = None
        self._keepalive_stop = threading.Event()
        self.keepalive_error: DeviceError | None = None
        self.parameters: ep.WidgetParameters | None = None
        self.serial_number: str | None = None

    @classmethod
    def from_url(
        cls,
        url: str,
        *,
        name: str = "dmx",
        serial: SerialSettings = DMX_SERIAL,
        universe_size: int = 512,
        verify_on_open: bool = True,
    ) -> EnttecDmx:
        """A widget on a serial URL; ``serial.timeout_s`` bounds every reply and every write."""
        transport = SerialTransport.from_settings(url, serial, name=name)
        return cls(transport, name=name, serial=serial, universe_size=universe_size, verify_on_open=verify_on_open)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> EnttecDmx:
        with self.lock:
            if self.is_open:
                return self
            self.transport.open()
            self._parser = ep.FrameParser()
            self.keepalive_error = None
            if self.verify_on_open:
                try:
                    self.get_widget_parameters()
                except BaseException:
                    self.transport.close()
                    raise
        return self

    def close(self) -> None:
        self.stop_keepalive()
        self.transport.close()

    def _require_open(self) -> None:
        if not self.is_open:
            raise DeviceGone(f"{self.name}: port {self.url} is not open — call open()")

    # ------------------------------------------------------------------ I/O
    def _take_unsolicited(self) -> None:
        """Read what arrived unasked; this is also what notices a closed TCP peer or a
        hung-up pty before we write into it."""
        for f in self._parser.feed(self.transport.read_available()):
            if len(self.unsolicited) < 256:
                self.unsolicited.append(f)

    def send_dmx(self, levels: bytes) -> None:
        """Send one universe (label 6, start code 0): ``levels[0]`` is channel 1; missing
        channels up to :attr:`universe_size` are 0.

        Raises
        ------
        InputError : more channels than the universe (nothing sent).
        DeviceGone : the port vanished; DeviceTimeout : the write did not complete.
        """
        try:
            levels = bytes(levels)
        except (TypeError, ValueError):
            raise InputError(f"{self.name}: DMX levels must be bytes or integers 0..255") from None
        if len(levels) > self.universe_size:
            raise InputError(f"{self.name}: {len(levels)} DMX channels given, the universe has {self.universe_size}")
        universe = levels + bytes(self.universe_size - len(levels))
        frame = ep.encode_send_dmx(universe)
        with self.lock:
            self._require_open()
            err, self.keepalive_error = self.keepalive_error, None
            if err is not None:
                raise DeviceGone(f"{self.name}: the background re-send failed earlier ({err})") from err
            self._take_unsolicited()
            self.transport.write(frame)
            self._last = universe
            self.packets_sent += 1

    @property
    def last_sent(self) -> bytes | None:
        """The last universe sent successfully (None before the first)."""
        return self._last

    def refresh(self) -> None:
        """Re-send the last universe (all zero if nothing was sent yet)."""
        self.send_dmx(self._last if self._last is not None else bytes(self.universe_size))

    def _request(self, frame: bytes, reply_label: int, what: str) -> ep.Frame:
        with self.lock:
            self._require_open()
            self._take_unsolicited()  # flush: a late reply must not answer this request
            self.transport.write(frame)
            mark = self.transport.mark()
            deadline = time.monotonic() + self.timeout_s
            while True:
                remaining = deadline - time.monotonic()
                if remaining > 0:
                    chunk = self.transport.read_some(timeout_s=remaining)
                    frames = self._parser.feed(chunk) if chunk else []
                else:  # out of time: give up on a half-received frame and rescan its bytes
                    frames = self._parser.abandon() if self._parser.pending else []
                for f in frames:
                    if f.label == reply_label:
                        return f
                    if len(self.unsolicited) < 256:
                        self.unsolicited.append(f)
                if remaining <= 0:
                    bad = self._parser.bad[-1:]
                    raise DeviceTimeout(
                        f"{self.name}: no {what} reply (label {reply_label}) within {self.timeout_s:.2f} s on "
                        f"{self.url}"
                        + (f" (last bad bytes: {bad[0].data[:24]!r})" if bad else "")
                        + f"; {self.transport.heard_since(mark)} — is it an Enttec DMX USB Pro (an Open DMX USB has "
                        "no processor and never answers), plugged in, and not used by another program?"
                    )

    def get_widget_parameters(self, user_config_size: int = 0) -> ep.WidgetParameters:
        """Label 3: firmware version, break/MAB times, output rate."""
        f = self._request(
            ep.encode_get_widget_parameters(user_config_size), ep.LABEL_GET_PARAMS, "Get Widget Parameters"
        )
        self.parameters = ep.parse_widget_parameters(f)
        return self.parameters

    def set_widget_parameters(self, *, break_time: int = 9, mab_time: int = 1, rate_hz: int = 40) -> None:
        """Label 4 (no reply): DMX break and MAB in 10.67 µs units, output rate packets/s."""
        frame = ep.encode_set_widget_parameters(break_time, mab_time, rate_hz)
        with self.lock:
            self._require_open()
            self._take_unsolicited()
            self.transport.write(frame)

    def get_serial_number(self) -> str:
        """Label 10: the serial printed on the case (BCD digits)."""
        f = self._request(ep.encode_get_serial(), ep.LABEL_GET_SERIAL, "Get Widget Serial Number")
        self.serial_number = ep.parse_serial(f)
        return self.serial_number

    # ------------------------------------------------------------------ keepalive
    def start_keepalive(self, period_s: float = 1.0) -> None:
        """Re-send the last universe every ``period_s`` in a daemon thread; the first
        failure is kept in :attr:`keepalive_error` and raised by the next :meth:`send_dmx`."""
        if self._keepalive is not None:
            return
        self._keepalive_stop.clear()

        def run():
            signals_off_this_thread()
            while not self._keepalive_stop.wait(period_s):
                try:
                    if self._last is not None:
                        with self.lock:
                            self._require_open()
                            self._take_unsolicited()
                            self.transport.write(ep.encode_send_dmx(self._last))
                except DeviceError as e:
                    log.warning("%s: keepalive stopped: %s", self.name, e)
                    self.keepalive_error = e
                    return

        self._keepalive = threading.Thread(target=run, name=f"{self.name}-keepalive", daemon=True)
        self._keepalive.start()

    def stop_keepalive(self) -> None:
        t, self._keepalive = self._keepalive, None
        if t is not None:
            self._keepalive_stop.set()
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    def check(self) -> DeviceInfo:
        """Widget parameters and serial number; never raises."""
        return check_opened(self, self._probe)

    def _probe(self) -> DeviceInfo:
        p = self.get_widget_parameters()
        sn = self.get_serial_number()
        fw = {1: "DMX", 2: "RDM", 3: "RDM sniffer"}.get(p.firmware[0], "unknown")
        return DeviceInfo(
            self.name,
            p.firmware[0] in (1, 2),
            f"firmware {p.firmware_version} ({fw}), break {p.break_us:.0f} us, MAB {p.mab_us:.0f} us, "
            f"{p.rate_hz or 'max'} packets/s on {self.url}",
            identity=f"Enttec DMX USB Pro serial {sn}",
            state={
                "serial": sn,
                "firmware": p.firmware_version,
                "break_us": p.break_us,
                "mab_us": p.mab_us,
                "rate_hz": p.rate_hz,
                "url": self.url,
                "packets_sent": self.packets_sent,
            },
        )


class DmxLightArray:
    """The overhead light array: lights on DMX channels of one widget, plus its rotation.

    Implements :class:`~opacityhull.rigs.interfaces.LightArray`.

    Parameters
    ----------
    dmx : the widget driver.
    channels : light id (``geometry.lights[].id``) -> 1-based DMX channel.
    rotation : the array's rotary axis (a :class:`~opacityhull.rigs.motion.GrblAxis`), or None.
    name : device name in messages.
    """

    def __init__(
        self,
        dmx: EnttecDmx,
        *,
        channels: Mapping[int, int],
        rotation: RotaryAxis | None = None,
        name: str = "light_array",
    ):
        self.name = name
        if not isinstance(channels, Mapping) or not channels:
            raise ConfigError(f"{name}: channels must be a non-empty table light id -> DMX channel, got {channels!r}")
        chans: dict[int, int] = {}
        for k, ch in channels.items():
            try:
                lid = int(k)  # TOML table keys are strings
            except (TypeError, ValueError):
                raise ConfigError(f"{name}: channels key {k!r} is not an integer light id") from None
            if isinstance(k, bool) or lid < 0 or str(lid) != str(k).strip():
                raise ConfigError(f"{name}: channels key {k!r} is not a light id (integer >= 0)")
            if isinstance(ch, bool) or not isinstance(ch, int) or not 1 <= ch <= dmx.universe_size:
                raise ConfigError(f"{name}: channels.{k} = {ch!r}, expected a DMX channel 1..{dmx.universe_size}")
            if lid in chans:
                raise ConfigError(f"{name}: light id {lid} appears twice in channels")
            chans[lid] = ch
        used: dict[int, int] = {}
        for lid, ch in chans.items():
            if ch in used:
                raise ConfigError(f"{name}: lights {used[ch]} and {lid} are both on DMX channel {ch}")
            used[ch] = lid
        self.dmx = dmx
        self.channels = dict(sorted(chans.items()))
        self._rotation = rotation
        self._levels = {lid: 0 for lid in self.channels}
        self.last_error: Exception | None = None

    # ------------------------------------------------------------------ LightArray
    @property
    def light_ids(self) -> tuple[int, ...]:
        return tuple(self.channels)

    @property
    def rotation(self) -> RotaryAxis | None:
        return self._rotation

    def open(self) -> DmxLightArray:
        """Open the widget (the rotation's controller is opened by its owner, the rig)."""
        self.dmx.open()
        return self

    def close(self) -> None:
        self.dmx.close()

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()
        return False

    def _validate(self, levels: Mapping[int, int]) -> dict[int, int]:
        if not isinstance(levels, Mapping):
            raise InputError(f"{self.name}: levels must be a mapping light id -> 0..255, got {type(levels).__name__}")
        out: dict[int, int] = {}
        for lid, v in levels.items():
            if isinstance(lid, bool) or not hasattr(lid, "__index__") or int(lid) not in self.channels:
                raise InputError(f"{self.name}: unknown light id {lid!r} (known ids: {list(self.channels)})")
            if isinstance(v, bool) or not hasattr(v, "__index__"):
                raise InputError(f"{self.name}: light {lid}: level {v!r} is not an integer 0..255")
            iv = int(v)
            if not 0 <= iv <= 255:
                raise InputError(f"{self.name}: light {lid}: level {v!r} is outside 0..255")
            out[int(lid)] = iv
        return out

    def _universe(self, levels: Mapping[int, int]) -> bytes:
        n = max(self.channels.values())
        u = bytearray(n)
        for lid, v in levels.items():
            u[self.channels[lid] - 1] = v
        return bytes(u)

    def set_levels(self, levels: Mapping[int, int]) -> None:
        """Set the given lights (id -> 0..255) and switch every other light off.

        Everything is validated before a byte is sent (:class:`InputError` naming the light
        and the value). A vanished widget raises :class:`DeviceGone`.
        """
        lv = self._validate(levels)
        full = {lid: lv.get(lid, 0) for lid in self.channels}
        self.dmx.send_dmx(self._universe(full))
        self._levels = full

    def all_off(self) -> None:
        """Every light off. Never raises (a failure is kept in :attr:`last_error`)."""
        try:
            self.dmx.send_dmx(bytes(max(self.channels.values())))
            self._levels = {lid: 0 for lid in self.channels}
            self.last_error = None
        except Exception as e:  # noqa: BLE001 - used from Rig.safe: must not mask the real error
            self.last_error = e

    def levels(self) -> dict[int, int]:
        """Last levels sent successfully, per light id."""
        return dict(self._levels)

    def refresh(self) -> None:
        """Send the current levels again (raises if the widget is gone)."""
        self.dmx.send_dmx(self._universe(self._levels))

    def check(self) -> DeviceInfo:
        """The widget's parameters and serial number (a live widget answers); never raises."""
        info = self.dmx.check()
        state = dict(info.state)
        state["levels"] = self.levels()
        state["channels"] = dict(self.channels)
        return DeviceInfo(self.name, info.ok, info.detail, identity=info.identity, state=state)
