"""Camera drivers implementing :class:`~opacityhull.rigs.interfaces.CameraDevice`.

* :class:`OpenCVCamera` — UVC webcams and machine-vision cameras that OpenCV's
  ``VideoCapture`` can open (a ``/dev/videoN`` index or path; any video file or image
  sequence OpenCV reads works too, which is how it is tested without hardware).
* :class:`DirectoryCamera` — tethered cameras whose vendor software (gphoto2,
  digiCamControl, a machine-vision SDK's recorder) writes each shot into a folder:
  ``capture`` notes the folder, optionally runs a trigger command, waits for a new
  file that has stopped growing, and reads it.

Both return linear float32 RGB (H, W, 3). Both open lazily: no I/O in ``__init__``.
"""

from __future__ import annotations

import fnmatch
import logging
import os
import re
import subprocess
import threading
import time
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import ConfigError, DeviceError, FormatError, InputError
from ..imageio import read_image, srgb_decode
from .interfaces import CameraInfo, DeviceInfo
from .transport import DeviceGone, DeviceTimeout, OpenClose

log = logging.getLogger(__name__)

__all__ = ["OpenCVCamera", "DirectoryCamera", "expand_braces"]

_LINEARIZE = ("srgb", "none")


def check_exposure(name: str, exposure_s) -> float:
    """``exposure_s`` as float seconds, or an InputError naming camera ``name`` (every
    camera driver, the simulated ones included, takes exposures through this)."""
    if (
        isinstance(exposure_s, bool)
        or not isinstance(exposure_s, (int, float, np.floating))
        or not np.isfinite(exposure_s)
        or exposure_s <= 0
    ):
        raise InputError(f"camera {name}: exposure_s must be a positive number of seconds, got {exposure_s!r}")
    return float(exposure_s)


def _to_rgb(name: str, a: np.ndarray) -> np.ndarray:
    """(H, W[, C]) → float32 (H, W, 3): grey is replicated, alpha dropped."""
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    elif a.shape[2] == 2:
        a = np.repeat(a[:, :, :1], 3, axis=2)
    elif a.shape[2] >= 3:
        a = a[:, :, :3]
    return np.ascontiguousarray(a, dtype=np.float32)


# =========================================================================== OpenCV (UVC)


class OpenCVCamera(OpenClose):
    """A camera read through ``cv2.VideoCapture``.

    Parameters
    ----------
    device : int or str
        Device index (``0`` = ``/dev/video0``), device path, or any source OpenCV can
        open (video file, ``frame_%03d.png`` image sequence, stream URL).
    name : str
    width, height : int
        Requested frame size; frames of any other size raise :class:`DeviceError`.
    linearize : "srgb" or "none"
        UVC cameras deliver sRGB-encoded 8-bit frames; ``"srgb"`` decodes them to linear
        light. ``"none"`` passes the values through (cameras configured for a linear
        response).
    white_level : float
        Value at and above which a returned pixel is saturated (reported in :meth:`info`
        for the HDR merge; the image is not rescaled).
    timeout_s : float
        Limit for opening the device and for each frame read.
    fourcc : str, optional
        Pixel format to request (``"MJPG"`` lets USB 2 cameras deliver full resolution).
    backend : str, optional
        ``"v4l2"``, ``"ffmpeg"``, ``"gstreamer"``, ``"dshow"``, ``"msmf"``, ``"images"``;
        default lets OpenCV choose.
    exposure_control : bool
        If True (default) every capture sets ``CAP_PROP_EXPOSURE`` and raises if the
        backend refuses. Set False for sources without exposure control (files, cameras
        fixed in their own software): the exposure argument is then only recorded.
    discard_frames : int, optional
        Frames thrown away after an exposure change before the one returned, so a frame
        exposed with the old setting (UVC drivers queue a few) is never used. Default: 2
        for devices, 0 for files.

    Notes
    -----
    ``CAP_PROP_EXPOSURE`` has no unit of its own; it is passed to the backend:

    * V4L2 (Linux UVC): ``V4L2_CID_EXPOSURE_ABSOLUTE`` in units of 100 µs, only in
      manual mode (``CAP_PROP_AUTO_EXPOSURE = 1``, which this driver sets; ``3`` is
      aperture priority). Many UVC cameras quantise the value or clamp it to the frame
      interval (1/fps): the value read back is checked and a mismatch beyond 5 %
      raises, naming the camera, rather than silently capturing a wrong exposure.
    * DirectShow / Media Foundation (Windows): log2 of seconds (``-5`` ≈ 1/32 s).
    * Files and image sequences: no exposure control.
    Gain, white balance and gamma should be fixed in the camera's own settings
    (``v4l2-ctl``); this driver only controls exposure.
    """

    def __init__(
        self,
        device,
        *,
        name: str = "camera",
        width: int,
        height: int,
        linearize: str = "srgb",
        white_level: float = 1.0,
        timeout_s: float = 5.0,
        fourcc: str | None = None,
        backend: str | None = None,
        exposure_control: bool = True,
        discard_frames: int | None = None,
    ):
        if isinstance(device, str) and device.strip().isdigit():
            device = int(device)
        if isinstance(device, bool) or not isinstance(device, (int, str, os.PathLike)):
            raise ConfigError(f"camera {name}: device must be an index or a path, got {device!r}")
        if linearize not in _LINEARIZE:
            raise ConfigError(f"camera {name}: linearize must be one of {_LINEARIZE}, got {linearize!r}")
        if fourcc is not None and (not isinstance(fourcc, str) or len(fourcc) != 4):
            raise ConfigError(f"camera {name}: fourcc must be 4 characters like 'MJPG', got {fourcc!r}")
        self.device = device if isinstance(device, int) else str(device)
        self.name = name
        self.width = int(width)
        self.height = int(height)
        self.linearize = linearize
        self.white_level = float(white_level)
        self.timeout_s = float(timeout_s)
        self.fourcc = fourcc
        self.backend = backend
        self.exposure_control = bool(exposure_control)
        self.discard_frames = (
            (2 if isinstance(self.device, int) or str(self.device).startswith("/dev/") else 0)
            if discard_frames is None
            else int(discard_frames)
        )
        self._cap = None
        self._exposure_s: float | None = None
        self._lock = threading.Lock()
        self.last_exposure_s: float | None = None

    # ---- lifecycle
    def _api(self) -> int:
        import cv2

        if self.backend is None:
            return cv2.CAP_ANY
        names = {
            "v4l2": "CAP_V4L2",
            "ffmpeg": "CAP_FFMPEG",
            "gstreamer": "CAP_GSTREAMER",
            "dshow": "CAP_DSHOW",
            "msmf": "CAP_MSMF",
            "images": "CAP_IMAGES",
            "any": "CAP_ANY",
        }
        if self.backend.lower() not in names:
            raise ConfigError(f"camera {self.name}: unknown backend {self.backend!r} (one of {sorted(names)})")
        return getattr(cv2, names[self.backend.lower()])

    def _where(self) -> str:
        if isinstance(self.device, int):
            return f"video device {self.device} (/dev/video{self.device})"
        return f"{self.device}"

    def open(self) -> OpenCVCamera:
        import cv2

        if self._cap is not None:
            return self
        if (
            isinstance(self.device, str)
            and not self.device.startswith(("/dev/", "rtsp:", "http:", "https:"))
            and "%" not in self.device
            and not Path(self.device).exists()
        ):
            raise DeviceGone(
                f"camera {self.name}: {self.device} does not exist — check the device path in [[devices.cameras]]"
            )
        ms = int(self.timeout_s * 1000)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
        cap = cv2.VideoCapture(self.device, self._api(), params)
        if not cap.isOpened():
            cap.release()
            raise DeviceGone(
                f"camera {self.name}: cannot open {self._where()} — is it plugged in, not used by another program, "
                "and readable by this user (group 'video')?"
            )
        if self.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # fewer stale frames after an exposure change
        self._cap = cap
        self._exposure_s = None
        return self

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    @property
    def backend_name(self) -> str:
        return self._cap.getBackendName() if self._cap is not None else ""

    def _require_cap(self):
        cap = self._cap
        if cap is None:
            raise DeviceGone(f"camera {self.name}: {self._where()} is not open — call open() first")
        return cap

    # ---- exposure
    def _set_exposure(self, exposure_s: float) -> None:
        import cv2

        cap = self._require_cap()
        be = cap.getBackendName().upper()
        if be == "V4L2":
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2_EXPOSURE_MANUAL
            value = exposure_s / 100e-6
        elif be in ("DSHOW", "MSMF"):
            value = float(np.log2(exposure_s))
        else:
            value = exposure_s
        accepted = cap.set(cv2.CAP_PROP_EXPOSURE, value)
        if not accepted:
            raise DeviceError(
                f"camera {self.name}: the {be} backend did not accept an exposure of {exposure_s} s on {self._where()} "
                "— put the camera in manual exposure mode, or set exposure_control = false in [[devices.cameras]] "
                "for a source whose exposure is fixed elsewhere"
            )
        readback = cap.get(cv2.CAP_PROP_EXPOSURE)
        if be == "V4L2" and readback > 0 and abs(readback - value) > 0.05 * value:
            raise DeviceError(
                f"camera {self.name}: asked for exposure {exposure_s} s ({value:.0f} × 100 µs), the camera set "
                f"{readback * 100e-6:.6g} s — outside its range at this frame rate? (lower the fps or the exposure)"
            )

    # ---- frames
    def _read_frame(self) -> np.ndarray:
        """One frame with a hard timeout (a wedged UVC driver can block ``read`` forever)."""
        cap = self._require_cap()
        box: dict = {}

        def work():
            try:
                box["r"] = cap.read()
            except Exception as e:  # noqa: BLE001  cv2.error or a backend's own: re-raised in the caller's thread
                box["e"] = e

        t = threading.Thread(target=work, name=f"read-{self.name}", daemon=True)
        t.start()
        t.join(self.timeout_s)
        if t.is_alive():
            self._cap = None  # the reader thread still owns it; open a fresh one next time
            raise DeviceTimeout(
                f"camera {self.name}: no frame from {self._where()} within {self.timeout_s} s — "
                "is the camera still connected (check dmesg) and the USB bandwidth sufficient?"
            )
        if "e" in box:
            raise DeviceError(f"camera {self.name}: reading {self._where()} failed ({box['e']})")
        ok, frame = box["r"]
        if not ok or frame is None:
            raise DeviceGone(
                f"camera {self.name}: {self._where()} delivered no frame (end of stream, or the device was unplugged)"
            )
        return frame

    def _convert(self, frame: np.ndarray) -> np.ndarray:
        if frame.ndim == 2:
            frame = frame[:, :, None]
        if frame.shape[0] != self.height or frame.shape[1] != self.width:
            raise DeviceError(
                f"camera {self.name}: {self._where()} delivers {frame.shape[1]}x{frame.shape[0]} frames, "
                f"the config asks for {self.width}x{self.height} — pick a size the camera supports"
            )
        if frame.shape[2] >= 3:
            frame = frame[:, :, [2, 1, 0]]  # OpenCV delivers BGR
        maxv = float(np.iinfo(frame.dtype).max) if np.issubdtype(frame.dtype, np.integer) else 1.0
        a = frame.astype(np.float32) / maxv
        if self.linearize == "srgb":
            a = srgb_decode(a)
        return _to_rgb(self.name, a)

    def capture(self, exposure_s: float) -> np.ndarray:
        """A frame exposed for ``exposure_s`` seconds: linear float32 RGB (height, width, 3)."""
        exposure_s = check_exposure(self.name, exposure_s)
        with self._lock:
            self.open()
            discard = 0
            if self.exposure_control and exposure_s != self._exposure_s:
                self._set_exposure(exposure_s)
                self._exposure_s = exposure_s
                discard = self.discard_frames
            for _ in range(discard):
                self._read_frame()
            img = self._convert(self._read_frame())
            self.last_exposure_s = exposure_s
            return img

    def info(self) -> CameraInfo:
        return CameraInfo(
            name=self.name,
            width=self.width,
            height=self.height,
            model=f"OpenCV VideoCapture {self.backend_name or self.backend or 'auto'}",
            serial=str(self.device),
            white_level=self.white_level,
            linear=True,
        )

    def check(self) -> DeviceInfo:
        """Open the device and read one frame (no exposure change); never raises."""
        try:
            with self._lock:
                self.open()
                frame = self._read_frame()
            h, w = frame.shape[:2]
        except (DeviceError, OSError) as e:
            return DeviceInfo(self.name, False, str(e))
        ok = (w, h) == (self.width, self.height)
        detail = f"{self.backend_name} {self._where()}: {w}x{h} frames"
        if not ok:
            detail += f", config asks for {self.width}x{self.height}"
        return DeviceInfo(
            self.name, ok, detail, identity=f"{self.backend_name}:{self.device}", state={"width": w, "height": h}
        )


# =========================================================================== tethered (folder)


def expand_braces(pattern: str) -> list[str]:
    """``"*.{exr,png}"`` → ``["*.exr", "*.png"]`` (one level of braces, like a shell)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    out = []
    for alt in m.group(1).split(","):
        out += expand_braces(pattern[: m.start()] + alt + pattern[m.end() :])
    return out


class DirectoryCamera:
    """A tethered camera whose software saves every shot into ``folder``.

    Parameters
    ----------
    folder : path
        Folder to watch (not recursive).
    name : str
    pattern : str
        Glob of image files to accept, with ``{a,b}`` alternatives; case-insensitive.
        Hidden files (``.tmp-...``, as atomic writers use) are ignored.
    timeout_s : float
        How long :meth:`capture` waits for a new, complete file.
    settle_s : float
        A file counts as complete when its size and mtime have not changed for this
        long (and it decodes; JPEGs must end with their EOI marker).
    trigger : sequence of str, or callable, optional
        Run after noting the folder: a command (``{exposure_s}`` and ``{folder}`` are
        substituted, e.g. ``["gphoto2", "--set-config-value", "shutterspeed={exposure_s}",
        "--capture-image-and-download", "--filename", "{folder}/%Y%m%d-%H%M%S-%f.%C"]``)
        or a function ``f(exposure_s)``. Without a trigger the shot is taken by someone
        else (the camera's software, an interval timer) and its exposure is whatever that
        uses; ``exposure_s`` is then only recorded.
    width, height : int, optional
        Expected image size; other sizes raise :class:`DeviceError`.
    linearize : "srgb" or "none"
        How 8/16-bit files (PNG/JPEG/TIFF) are decoded; EXR/HDR are linear already.
    white_level : float
        Saturation value of the returned images (reported in :meth:`info`).
    poll_s : float
        Folder polling interval.
    on_wait : callable, optional
        ``f(state, path, size)`` called while waiting, ``state`` one of ``"waiting"``,
        ``"growing"``, ``"unreadable"``, ``"done"`` (progress display, tests).
    """

    def __init__(
        self,
        folder,
        *,
        name: str = "camera",
        pattern: str = "*.{exr,png,jpg,jpeg,tif,tiff}",
        timeout_s: float = 30.0,
        settle_s: float = 0.2,
        trigger: Sequence[str] | Callable | None = None,
        width: int | None = None,
        height: int | None = None,
        linearize: str = "srgb",
        white_level: float = 1.0,
        poll_s: float = 0.01,
        on_wait: Callable[[str, Path | None, int], None] | None = None,
    ):
        if linearize not in _LINEARIZE:
            raise ConfigError(f"camera {name}: linearize must be one of {_LINEARIZE}, got {linearize!r}")
        if (
            trigger is not None
            and not callable(trigger)
            and (isinstance(trigger, str) or not all(isinstance(x, str) for x in trigger))
        ):
            raise ConfigError(f"camera {name}: trigger must be a list of strings (a command), got {trigger!r}")
        self.folder = Path(folder)
        self.name = name
        self.pattern = pattern
        self._globs = [g.lower() for g in expand_braces(pattern)]
        self.timeout_s = float(timeout_s)
        self.settle_s = float(settle_s)
        self.trigger = trigger
        self.width = width
        self.height = height
        self.linearize = linearize
        self.white_level = float(white_level)
        self.poll_s = float(poll_s)
        self.on_wait = on_wait
        self.last_path: Path | None = None
        self.last_exposure_s: float | None = None

    def open(self) -> DirectoryCamera:
        if not self.folder.is_dir():
            raise DeviceGone(
                f"camera {self.name}: folder {self.folder} does not exist — create it and point the "
                "tethering software at it"
            )
        return self

    def close(self) -> None:
        pass

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        return False

    def _matches(self, fname: str) -> bool:
        if fname.startswith("."):
            return False
        low = fname.lower()
        return any(fnmatch.fnmatchcase(low, g) for g in self._globs)

    def _scan(self) -> dict[str, tuple[int, int]]:
        out = {}
        try:
            entries = list(os.scandir(self.folder))
        except OSError as e:
            raise DeviceGone(f"camera {self.name}: cannot read folder {self.folder} ({e})") from None
        for e in entries:
            if self._matches(e.name):
                try:
                    st = e.stat()
                except OSError:  # renamed/deleted between scandir and stat
                    continue
                if e.is_file():
                    out[e.name] = (st.st_size, st.st_mtime_ns)
        return out

    def _run_trigger(self, exposure_s: float) -> None:
        if self.trigger is None:
            return
        if callable(self.trigger):
            self.trigger(exposure_s)
            return
        cmd = [a.replace("{exposure_s}", f"{exposure_s:g}").replace("{folder}", str(self.folder)) for a in self.trigger]
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=self.timeout_s)
        except FileNotFoundError:
            raise DeviceError(f"camera {self.name}: trigger command {cmd[0]!r} not found — is it installed?") from None
        except subprocess.TimeoutExpired:
            raise DeviceTimeout(
                f"camera {self.name}: trigger command {' '.join(cmd)} did not finish within "
                f"{self.timeout_s} s — is the camera connected and awake?"
            ) from None
        if r.returncode != 0:
            raise DeviceError(
                f"camera {self.name}: trigger command {' '.join(cmd)} failed with exit code "
                f"{r.returncode}: {r.stderr.strip()[-300:]}"
            )

    def _notify(self, state: str, path: Path | None, size: int) -> None:
        if self.on_wait is not None:
            self.on_wait(state, path, size)

    def _read(self, path: Path) -> np.ndarray | None:
        """The image, or None if it is not (yet) complete/decodable."""
        suffix = path.suffix.lower()
        if suffix in (".jpg", ".jpeg"):
            try:
                with open(path, "rb") as f:
                    f.seek(-2, os.SEEK_END)
                    if f.read(2) != b"\xff\xd9":  # a JPEG without EOI is still being written
                        return None
            except OSError:
                return None
        try:
            if suffix in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
                return read_image(path, linear=(self.linearize == "none"))
            return read_image(path)
        except (FormatError, OSError):
            return None
        except InputError:
            raise DeviceError(f"camera {self.name}: {path} has an image type opacityhull cannot read") from None

    def capture(self, exposure_s: float) -> np.ndarray:
        """Wait for the next new image in the folder; linear float32 RGB (H, W, 3)."""
        exposure_s = check_exposure(self.name, exposure_s)
        self.open()
        before = self._scan()
        self._run_trigger(exposure_s)
        deadline = time.monotonic() + self.timeout_s
        seen: dict[str, tuple[tuple[int, int], float]] = {}  # name -> (stat, time it last changed)
        unreadable: set[str] = set()
        while True:
            now = time.monotonic()
            current = self._scan()
            new = {n: s for n, s in current.items() if before.get(n) != s}
            # oldest first: the first file written is this shot, later ones belong to later shots
            for fname in sorted(new, key=lambda n: (new[n][1], n)):
                st = new[fname]
                prev = seen.get(fname)
                if prev is None or prev[0] != st:
                    seen[fname] = (st, now)
                    unreadable.discard(fname)
                    self._notify("growing", self.folder / fname, st[0])
                    continue
                if now - prev[1] < self.settle_s or fname in unreadable:
                    continue
                img = self._read(self.folder / fname)
                if img is None:
                    unreadable.add(fname)  # retried only once it changes again
                    self._notify("unreadable", self.folder / fname, st[0])
                    continue
                return self._finish(self.folder / fname, img, exposure_s)
            if not new:
                self._notify("waiting", None, 0)
            if now >= deadline:
                break
            time.sleep(self.poll_s)  # polling a folder: inotify is not portable
        if seen:
            names = ", ".join(sorted(seen))
            raise DeviceTimeout(
                f"camera {self.name}: new file(s) {names} in {self.folder} did not become a complete, readable image "
                f"within {self.timeout_s} s — is the camera software still writing, or saving a format other than "
                f"{self.pattern}?"
            )
        raise DeviceTimeout(
            f"camera {self.name}: no new image matching {self.pattern} appeared in {self.folder} within "
            f"{self.timeout_s} s — is the tethering software running, the camera on, and saving into this folder?"
        )

    def _finish(self, path: Path, img: np.ndarray, exposure_s: float) -> np.ndarray:
        rgb = _to_rgb(self.name, img)
        if self.width is not None and self.height is not None and rgb.shape[:2] != (self.height, self.width):
            raise DeviceError(
                f"camera {self.name}: {path} is {rgb.shape[1]}x{rgb.shape[0]}, the config asks for "
                f"{self.width}x{self.height} — check the camera's image size setting"
            )
        self.last_path = path
        self.last_exposure_s = exposure_s
        self._notify("done", path, path.stat().st_size)
        return rgb

    def info(self) -> CameraInfo:
        return CameraInfo(
            name=self.name,
            width=int(self.width or 0),
            height=int(self.height or 0),
            model=f"tethered camera writing to {self.folder}",
            serial="",
            white_level=self.white_level,
            linear=True,
        )

    def check(self) -> DeviceInfo:
        """The folder exists and is writable (the camera itself is only seen when it shoots)."""
        if not self.folder.is_dir():
            return DeviceInfo(self.name, False, f"folder {self.folder} does not exist")
        if not os.access(self.folder, os.W_OK | os.X_OK):
            return DeviceInfo(self.name, False, f"folder {self.folder} is not writable")
        n = len(self._scan())
        return DeviceInfo(
            self.name,
            True,
            f"watching {self.folder} ({n} image(s) there now)",
            identity=f"directory:{self.folder}",
            state={"files": n},
        )
