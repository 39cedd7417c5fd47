"""Emulator of a signage display's MDC control port: the same bytes as a Samsung panel.

Answers the commands of :mod:`opacityhull.rigs.mdc_protocol` addressed to its ID
(frames for other IDs are another panel's on the daisy chain: ignored; the broadcast
ID is obeyed and never answered), with the reply faults of
:class:`~opacityhull.rigs.emulators.base.Faults` and the server's ``vanish()`` like
every emulator, plus:

* ``locked`` — settings (``"brightness"``, ``"contrast"``, ``"energy_saving"``, ...)
  the panel refuses to change: a SET is NAKed (as a panel with its safety lock on);
* ``corrupt_rx`` — the next N frames are taken as failing their checksum (ignored, as a
  panel ignores a frame it cannot read: the host times out and resends);
* the emulator's own vendor commands :data:`EMU_PICTURE_MODE_CMD` and
  :data:`EMU_DYNAMIC_CONTRAST_CMD` (the cited MDC document has neither; a real panel's
  codes come from its own document).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from .. import mdc_protocol as mdc
from .base import EmulatedDevice, Reply

log = logging.getLogger(__name__)

__all__ = ["MdcEmulator", "EMU_PICTURE_MODE_CMD", "EMU_DYNAMIC_CONTRAST_CMD", "NAK_LOCKED", "NAK_UNSUPPORTED"]

#: Vendor command codes of the emulated panel only.
EMU_PICTURE_MODE_CMD = 0xE0
EMU_DYNAMIC_CONTRAST_CMD = 0xE1
#: The emulator's NAK error bytes (the document leaves ERR model-specific).
NAK_LOCKED = 0x01
NAK_UNSUPPORTED = 0x02

_SETTINGS = {
    mdc.CMD_POWER: "power",
    mdc.CMD_INPUT: "input",
    mdc.CMD_CONTRAST: "contrast",
    mdc.CMD_BRIGHTNESS: "brightness",
    mdc.CMD_MANUAL_LAMP: "backlight",
    mdc.CMD_ENERGY_SAVING: "energy_saving",
    EMU_PICTURE_MODE_CMD: "picture_mode",
    EMU_DYNAMIC_CONTRAST_CMD: "dynamic_contrast",
}


class MdcEmulator(EmulatedDevice):
    """A signage panel's RS-232 control port.

    Parameters
    ----------
    display_id : int
        Its MDC ID (0..253).
    model : str
        What MODEL NAME answers.
    energy_saving, dynamic_contrast, auto_lamp :
        Factory state: a panel out of the box dims itself (energy saving ``low``,
        dynamic contrast on) until the driver locks it.
    temperature_c : int
    """

    name = "mdc"

    def __init__(
        self,
        *,
        display_id: int = 1,
        model: str = "QM55R-EMU",
        energy_saving: int = 0x01,
        dynamic_contrast: int = 1,
        auto_lamp: bool = False,
        temperature_c: int = 38,
        time_scale: float = 0.0,
    ):
        super().__init__(time_scale=time_scale)
        self.display_id = mdc.check_display_id(display_id, where="MdcEmulator")
        self.model = model
        self.values: dict[str, int] = {
            "power": 0,
            "input": mdc.INPUT_SOURCES["hdmi1"],
            "contrast": 75,
            "brightness": 50,
            "backlight": 70,
            "energy_saving": int(energy_saving),
            "picture_mode": 0,
            "dynamic_contrast": int(dynamic_contrast),
        }
        self.auto_lamp = bool(auto_lamp)
        self.temperature_c = int(temperature_c)
        self.locked: set[str] = set()
        self.corrupt_rx = 0
        self.history: list[mdc.Command] = []
        self._parser = mdc.FrameParser()

    # ---- state accessors (thread-safe)
    def value(self, setting: str) -> int:
        with self.lock:
            return self.values[setting]

    def drifting(self) -> bool:
        """True while the panel may change its own radiance (what the driver must lock)."""
        with self.lock:
            return self.values["energy_saving"] != 0 or bool(self.values["dynamic_contrast"]) or self.auto_lamp

    # ---- wire side
    def receive(self, data: bytes) -> Iterable[Reply]:
        out: list[Reply] = []
        for item in self._parser.feed(data):
            if not isinstance(item, mdc.Command):
                continue  # noise, a bad checksum, a reply of another panel: a panel stays silent
            if item.display_id not in (self.display_id, mdc.BROADCAST_ID):
                continue
            if self.corrupt_rx > 0:
                self.corrupt_rx -= 1
                continue
            self.history.append(item)
            ack, rdata = self._handle(item)
            if item.display_id == mdc.BROADCAST_ID:
                continue
            out.append(Reply(mdc.encode_reply(self.display_id, item.cmd, rdata, ack=ack)))
        return out

    def _handle(self, c: mdc.Command) -> tuple[bool, bytes]:
        v = self.values
        if c.cmd == mdc.CMD_MODEL_NAME and not c.data:
            return True, self.model.encode("ascii")
        if c.cmd == mdc.CMD_ERROR_STATUS and not c.data:
            sensor = "normal"
            return True, mdc.ErrorStatus(False, False, sensor, v["power"] == 0, self.temperature_c, "normal").encode()
        if c.cmd == mdc.CMD_AUTO_LAMP:
            lo = 0 if self.auto_lamp else v["backlight"]
            return True, bytes((8, 0, 1, v["backlight"], 8, 0, 0, lo))
        setting = _SETTINGS.get(c.cmd)
        if setting is None:
            return False, bytes((NAK_UNSUPPORTED,))
        if not c.data:
            return True, bytes((v[setting],))
        if len(c.data) != 1:
            return False, bytes((NAK_UNSUPPORTED,))
        if setting in self.locked and c.data[0] != v[setting]:
            return False, bytes((NAK_LOCKED,))
        x = c.data[0]
        if setting in ("brightness", "contrast", "backlight") and x > 100:
            return False, bytes((NAK_UNSUPPORTED,))
        v[setting] = x
        if setting == "backlight":
            self.auto_lamp = False  # the document: manual lamp control turns auto lamp off
        return True, bytes((x,))
