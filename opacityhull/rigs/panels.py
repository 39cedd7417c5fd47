"""Driver of a signage display's RS-232 control port: Samsung MDC.

Transport: any :class:`~opacityhull.rigs.transport.Transport` (``from_url``: a serial
one); wire protocol: :mod:`opacityhull.rigs.mdc_protocol` (``docs/mdc-protocol.md``).
The picture itself arrives over the video cable (:mod:`opacityhull.rigs.video`); this
port sets what changes the picture's radiance: power, input source, brightness,
contrast, the backlight (manual, not scheduled) and energy saving (off), and reads the
panel's status and temperature.

One command at a time; a reply that does not come, comes garbled or answers another
panel is a resend of the same frame (every command states an absolute value) up to
``retries`` times; a NAK is final and names the setting, since a panel NAKs a value it
will not take (a setting locked by the panel's safety lock, a picture mode that fixes
it, or a command this model lacks).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from ..errors import ConfigError, DeviceError, InputError
from . import mdc_protocol as mdc
from .interfaces import DeviceInfo, DisplayDrift
from .transport import DeviceGone, DeviceTimeout, OverTransport, ProtocolError, SerialSettings, SerialTransport
from .transport import Transport, driver_name, reopen

log = logging.getLogger(__name__)

__all__ = ["MDC_SERIAL", "DisplayDrift", "MdcPanel", "PanelNak", "PanelSettings", "PanelState"]

#: 9600 8N1 as the MDC document specifies; 1 s per reply, 2 resends, 2 re-opens.
MDC_SERIAL = SerialSettings(baudrate=9600, timeout_s=1.0, retries=2, reconnect_attempts=2, reconnect_delay_s=0.2)


class PanelNak(ProtocolError):
    """The panel refused a command (NAK); :attr:`error` is its error byte."""

    def __init__(self, message: str, error: int):
        super().__init__(message)
        self.error = error


@dataclass(frozen=True, kw_only=True)
class PanelSettings:
    """What a capture locks on a panel (the rig TOML's ``[devices.panels.NAME]``).

    Attributes
    ----------
    input : str
        Input source the video output is plugged into (:data:`mdc_protocol.INPUT_SOURCES`).
    brightness, contrast : int
        0..100.
    backlight : int or None
        Manual backlight 0..100 (MANUAL LAMP; setting it turns the scheduled AUTO LAMP
        off); None leaves the backlight as it is.
    picture_mode : (command, value) or None
        The panel's picture-mode command code and the value to lock, from the panel's
        own MDC document (the cited protocol document has no picture-mode command).
    dynamic_contrast_cmd : int or None
        The panel's dynamic-contrast command code (value 0 = off), from its MDC
        document; None: the panel's dynamic contrast cannot be read over MDC and is
        reported as unverified.
    """

    input: str = "hdmi1"
    brightness: int = 100
    contrast: int = 100
    backlight: int | None = None
    picture_mode: tuple[int, int] | None = None
    dynamic_contrast_cmd: int | None = None

    def __post_init__(self) -> None:
        if self.input not in mdc.INPUT_SOURCES:
            raise ConfigError(f"panel input {self.input!r}: expected one of {sorted(mdc.INPUT_SOURCES)}")
        for key in ("brightness", "contrast", "backlight"):
            v = getattr(self, key)
            if v is None and key == "backlight":
                continue
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 100:
                raise ConfigError(f"panel {key} = {v!r}: expected an integer 0..100")
        for key, v in (("picture_mode", self.picture_mode), ("dynamic_contrast_cmd", self.dynamic_contrast_cmd)):
            vals = v if isinstance(v, tuple) else (v,) if v is not None else ()
            if any(isinstance(x, bool) or not isinstance(x, int) or not 0 <= x <= 0xFE for x in vals):
                raise ConfigError(f"panel {key} = {v!r}: expected byte value(s) 0..254 from the panel's MDC document")


@dataclass(frozen=True)
class PanelState:
    """What the panel reports: identity, the settings that drive its radiance, status.

    ``drift`` lists, in words, every setting that lets the panel change its own radiance
    between shots (energy saving on, a backlight schedule, dynamic contrast on);
    ``unverified`` the ones this panel cannot report over MDC.
    """

    model: str
    power: bool
    input: str
    brightness: int
    contrast: int
    energy_saving: str
    auto_lamp: bool
    dynamic_contrast: bool | None
    picture_mode: int | None
    temperature_c: int
    no_sync: bool
    drift: tuple[str, ...] = ()
    unverified: tuple[str, ...] = field(default=())


def _name_of(table: dict[str, int], code: int) -> str:
    for k, v in table.items():
        if v == code:
            return k
    return f"0x{code:02X}"


class MdcPanel(OverTransport):
    """One display's MDC control port.

    Parameters
    ----------
    transport : Transport
    display_id : int
        The panel's MDC ID, 0..253 (:func:`mdc_protocol.check_display_id`).
    name : str, optional
        Device name in messages (default: the transport's).
    serial : SerialSettings
        Default :data:`MDC_SERIAL`.
    settings : PanelSettings
        What :meth:`lock` sets.

    No I/O happens in ``__init__``.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        display_id: int,
        name: str | None = None,
        serial: SerialSettings = MDC_SERIAL,
        settings: PanelSettings = PanelSettings(),
    ):
        name = driver_name(transport, name, driver="MdcPanel", fallback="panel")
        self.display_id = mdc.check_display_id(display_id, where=f"{name}: id")
        self.name = name
        self.transport = transport
        self.settings = settings
        self.timeout_s = float(serial.timeout_s)
        self.retries = serial.retries
        self.reconnect_attempts = serial.reconnect_attempts
        self.reconnect_delay_s = float(serial.reconnect_delay_s)
        self._parser = mdc.FrameParser()
        self.stats = {"frames": 0, "resends": 0, "naks": 0, "reconnects": 0}

    @classmethod
    def from_url(
        cls,
        url: str,
        *,
        display_id: int,
        name: str = "panel",
        serial: SerialSettings = MDC_SERIAL,
        settings: PanelSettings = PanelSettings(),
    ) -> MdcPanel:
        transport = SerialTransport.from_settings(url, serial, name=name)
        return cls(transport, display_id=display_id, name=name, serial=serial, settings=settings)

    # ---- lifecycle
    def open(self) -> MdcPanel:
        self.transport.open()
        self._parser.reset()
        return self

    def close(self) -> None:
        self.transport.close()

    def reconnect(self) -> None:
        def once(attempt: int) -> None:
            self.transport.close()
            self.open()
            self.stats["reconnects"] += 1

        def gave_up(tries: int, last: BaseException | None) -> DeviceGone:
            return DeviceGone(
                f"{self.name}: port {self.url} did not come back after {tries} attempt(s) ({last}) — check the "
                "RS-232 cable to the panel's RS232C IN and that the panel has mains power"
            )

        reopen(once, attempts=self.reconnect_attempts, delay_s=self.reconnect_delay_s, gave_up=gave_up)

    # ---- protocol core
    def _transact(self, cmd: int, data: bytes = b"", *, what: str = "") -> bytes:
        """Send one command; the ACK's values. Resends on timeout or garbage; a NAK raises."""
        what = what or mdc.COMMAND_NAMES.get(cmd, f"0x{cmd:02X}")
        frame = mdc.encode_command(cmd, self.display_id, data)
        mark = self.transport.mark()
        problems: list[str] = []
        reconnects = 0
        with self.transport.exchange(self.timeout_s * (self.retries + 1), what):
            attempt = 0
            while attempt <= self.retries:
                try:
                    if not self.transport.is_open:
                        self.open()
                    self.transport.flush_input()
                    self._parser.reset()
                    self.transport.write(frame)
                    self.stats["frames"] += 1
                    reply = self._await_reply(cmd)
                except DeviceGone:
                    if reconnects >= self.reconnect_attempts:
                        raise
                    reconnects += 1
                    self.reconnect()
                    continue
                except DeviceTimeout as e:
                    problems.append(str(e).split(" — ")[0])
                    attempt += 1
                    self.stats["resends"] += 1
                    continue
                if reply.ack:
                    return reply.data
                self.stats["naks"] += 1
                err = reply.data[0] if reply.data else -1
                raise PanelNak(
                    f"{self.name}: panel (MDC id {self.display_id}) refused {what} (NAK, error 0x{err & 0xFF:02X}) — "
                    "the setting may be locked (safety lock, a picture mode that fixes it, MagicInfo) or this "
                    "model lacks the command: unlock it in the panel's menu or check its MDC document",
                    err,
                )
        raise DeviceTimeout(
            f"{self.name}: no valid reply to {what} after {self.retries + 1} attempt(s) on {self.url} "
            f"({'; '.join(dict.fromkeys(problems))}); {self.transport.heard_since(mark)} — check the RS-232 cable "
            f"(RS232C IN, a null-modem cable), the baud rate ({self.transport.baudrate}), that MDC connection is set "
            f"to RS232C and that the panel's ID is {self.display_id}"
        )

    def _await_reply(self, cmd: int) -> mdc.Reply:
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = self.transport._clamp(deadline) - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"{self.name}: no reply within {self.timeout_s:g} s on {self.url}")
            chunk = self.transport.read_some(timeout_s=remaining)
            for item in self._parser.feed(chunk):
                if isinstance(item, mdc.BadFrame):
                    log.debug("%s: skipped %s bytes %r", self.name, item.reason, item.data[:16])
                    continue
                if isinstance(item, mdc.Reply) and item.display_id == self.display_id and item.rcmd == cmd:
                    return item
                log.debug("%s: skipped %r (another panel or a late reply)", self.name, item)

    # ---- commands
    def _set(self, cmd: int, value: int, what: str) -> int:
        got = self._transact(cmd, bytes((value,)), what=f"SET {what} {value}")
        if got[:1] != bytes((value,)):
            raise ProtocolError(
                f"{self.name}: SET {what} {value} was acknowledged with {got.hex(' ') or 'no value'} — the panel "
                "did not take the value (is the setting locked?)"
            )
        return value

    def _get1(self, cmd: int, what: str) -> int:
        got = self._transact(cmd, what=f"GET {what}")
        if not got:
            raise ProtocolError(f"{self.name}: GET {what}: the ACK carries no value")
        return got[0]

    def model_name(self) -> str:
        return self._transact(mdc.CMD_MODEL_NAME, what="GET MODEL NAME").rstrip(b"\0").decode("ascii", "replace")

    def power(self, on: bool) -> None:
        self._set(mdc.CMD_POWER, 1 if on else 0, "POWER")

    def powered(self) -> bool:
        return self._get1(mdc.CMD_POWER, "POWER") == 1

    def set_input(self, source: str) -> None:
        code = mdc.INPUT_SOURCES.get(source)
        if code is None:
            raise InputError(f"{self.name}: unknown input source {source!r} (one of {sorted(mdc.INPUT_SOURCES)})")
        self._set(mdc.CMD_INPUT, code, "INPUT SOURCE")

    def set_brightness(self, value: int) -> None:
        self._set(mdc.CMD_BRIGHTNESS, _level(value, "brightness", self.name), "BRIGHTNESS")

    def set_contrast(self, value: int) -> None:
        self._set(mdc.CMD_CONTRAST, _level(value, "contrast", self.name), "CONTRAST")

    def set_backlight(self, value: int) -> None:
        self._set(mdc.CMD_MANUAL_LAMP, _level(value, "backlight", self.name), "MANUAL LAMP")

    def energy_saving_off(self) -> None:
        self._set(mdc.CMD_ENERGY_SAVING, mdc.ENERGY_SAVING["off"], "ENERGY SAVING")

    def error_status(self) -> mdc.ErrorStatus:
        try:
            return mdc.parse_error_status(self._transact(mdc.CMD_ERROR_STATUS, what="GET DISPLAY STATUS"))
        except InputError as e:
            raise ProtocolError(f"{self.name}: {e}") from None

    def lock(self) -> PanelState:
        """Power on and set every radiance-relevant setting of :attr:`settings`; then read
        them back (:meth:`state`). A NAK raises :class:`PanelNak` naming the setting."""
        s = self.settings
        self.power(True)
        self.set_input(s.input)
        self.energy_saving_off()
        if s.backlight is not None:
            self.set_backlight(s.backlight)
        self.set_brightness(s.brightness)
        self.set_contrast(s.contrast)
        if s.picture_mode is not None:
            self._set(s.picture_mode[0], s.picture_mode[1], "PICTURE MODE")
        if s.dynamic_contrast_cmd is not None:
            self._set(s.dynamic_contrast_cmd, 0, "DYNAMIC CONTRAST")
        return self.state()

    def state(self) -> PanelState:
        """Everything :class:`PanelState` holds, read from the panel."""
        s = self.settings
        model = self.model_name()
        power = self.powered()
        source = _name_of(mdc.INPUT_SOURCES, self._get1(mdc.CMD_INPUT, "INPUT SOURCE"))
        brightness = self._get1(mdc.CMD_BRIGHTNESS, "BRIGHTNESS")
        contrast = self._get1(mdc.CMD_CONTRAST, "CONTRAST")
        es = _name_of(mdc.ENERGY_SAVING, self._get1(mdc.CMD_ENERGY_SAVING, "ENERGY SAVING"))
        lamp = self._transact(mdc.CMD_AUTO_LAMP, what="GET AUTO LAMP")
        # AUTO LAMP holds max time, max value, min time, min value; equal values (or an
        # all-zero schedule) mean the backlight does not follow the clock
        auto_lamp = len(lamp) >= 8 and lamp[3] != lamp[7]
        dyn = None if s.dynamic_contrast_cmd is None else self._get1(s.dynamic_contrast_cmd, "DYNAMIC CONTRAST") != 0
        pm = None if s.picture_mode is None else self._get1(s.picture_mode[0], "PICTURE MODE")
        st = self.error_status()
        drift = []
        if es != "off":
            drift.append(f"energy saving {es} (auto-brightness)")
        if auto_lamp:
            drift.append("backlight schedule (AUTO LAMP)")
        if dyn:
            drift.append("dynamic contrast on")
        unverified = () if s.dynamic_contrast_cmd is not None else ("dynamic contrast (no MDC command configured)",)
        return PanelState(
            model=model,
            power=power,
            input=source,
            brightness=brightness,
            contrast=contrast,
            energy_saving=es,
            auto_lamp=auto_lamp,
            dynamic_contrast=dyn,
            picture_mode=pm,
            temperature_c=st.temperature_c,
            no_sync=st.no_sync,
            drift=tuple(drift),
            unverified=unverified,
        )

    def check(self) -> DeviceInfo:
        """Model, mode and locks (``rig check``); never raises."""
        try:
            st = self.state()
        except (DeviceError, OSError) as e:
            return DeviceInfo(self.name, False, str(e), state={"url": self.url})
        locks = "locked" if not st.drift else "DRIFTS: " + ", ".join(st.drift)
        detail = (
            f"{st.model} (MDC id {self.display_id}); {'on' if st.power else 'off'}, input {st.input}, "
            f"brightness {st.brightness}, contrast {st.contrast}, energy saving {st.energy_saving}, "
            f"{st.temperature_c} °C; {locks}"
        )
        if st.unverified:
            detail += "; unverified: " + ", ".join(st.unverified)
        state = {k: getattr(st, k) for k in st.__dataclass_fields__}
        state["url"] = self.url
        return DeviceInfo(self.name, True, detail, identity=st.model, state=state)


def _level(value: int, what: str, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 100:
        raise InputError(f"{name}: {what} must be an integer 0..100, got {value!r}")
    return value
