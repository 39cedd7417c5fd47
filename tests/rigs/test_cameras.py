"""Camera drivers: OpenCV against real video sources OpenCV opens without hardware, and the
tethered-folder camera against a real writer thread / subprocess."""

import sys
import threading

import numpy as np
import pytest

from opacityhull.errors import DeviceError, InputError
from opacityhull.imageio import read_png, srgb_decode, write_exr, write_png
from opacityhull.rigs.cameras import DirectoryCamera, OpenCVCamera, expand_braces
from opacityhull.rigs.interfaces import CameraDevice
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout

cv2 = pytest.importorskip("cv2")

W, H = 32, 24


def frame_bgr(i: int) -> np.ndarray:
    """A test frame with distinct R, G, B ramps (so a channel swap is visible)."""
    y, x = np.mgrid[0:H, 0:W]
    r = (x * 7 + i * 10) % 256
    g = (y * 9 + 3 * i) % 256
    b = np.full_like(x, 200 - i * 20)
    return np.stack([b, g, r], -1).astype(np.uint8)


@pytest.fixture(scope="module")
def image_sequence(tmp_path_factory):
    d = tmp_path_factory.mktemp("seq")
    for i in range(3):
        assert cv2.imwrite(str(d / f"frame_{i:03d}.png"), frame_bgr(i))
    return str(d / "frame_%03d.png")


@pytest.fixture(scope="module")
def avi(tmp_path_factory):
    p = tmp_path_factory.mktemp("avi") / "clip.avi"
    w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W, H))
    assert w.isOpened()
    for i in range(4):
        w.write(np.full((H, W, 3), 40 + 50 * i, np.uint8))
    w.release()
    return p


def test_opencv_image_sequence_exact_linear_rgb(image_sequence):
    cam = OpenCVCamera(image_sequence, name="cam0", width=W, height=H, exposure_control=False, timeout_s=5)
    assert isinstance(cam, CameraDevice)
    with cam:
        for i in range(3):
            img = cam.capture(0.01)
            assert img.dtype == np.float32 and img.shape == (H, W, 3)
            expected = srgb_decode(frame_bgr(i)[:, :, ::-1].astype(np.float32) / 255.0)
            np.testing.assert_allclose(img, expected, rtol=0, atol=1e-6)
        with pytest.raises(DeviceGone, match="cam0: .*delivered no frame"):
            cam.capture(0.01)  # end of the sequence
    info = cam.info()
    assert (info.name, info.width, info.height, info.linear) == ("cam0", W, H, True)


def test_opencv_linearize_none_passes_values_through(image_sequence):
    with OpenCVCamera(image_sequence, name="c", width=W, height=H, linearize="none", exposure_control=False) as cam:
        img = cam.capture(0.02)
    np.testing.assert_allclose(img, frame_bgr(0)[:, :, ::-1] / 255.0, atol=1e-6)


def test_opencv_avi_frames_in_order(avi):
    with OpenCVCamera(str(avi), name="c", width=W, height=H, linearize="none", exposure_control=False) as cam:
        means = [float(cam.capture(0.01).mean()) * 255 for _ in range(4)]
    # MJPG is lossy: grey levels within a few codes, and strictly in write order
    np.testing.assert_allclose(means, [40, 90, 140, 190], atol=4)


def test_opencv_exposure_control_refused_by_file_backend(avi):
    cam = OpenCVCamera(str(avi), name="cam3", width=W, height=H)
    with pytest.raises(
        DeviceError, match=r"cam3: the \w+ backend did not accept an exposure of 0.01 s.*exposure_control = false"
    ):
        cam.capture(0.01)
    cam.close()


def test_opencv_missing_devices_give_clear_errors(tmp_path):
    cam = OpenCVCamera(57, name="cam1", width=W, height=H, timeout_s=1)
    with pytest.raises(
        DeviceGone, match=r"camera cam1: cannot open video device 57 \(/dev/video57\) — is it plugged in"
    ):
        cam.capture(0.01)
    info = cam.check()
    assert not info.ok and "video device 57" in info.detail
    cam2 = OpenCVCamera(str(tmp_path / "nope.avi"), name="cam2", width=W, height=H)
    with pytest.raises(DeviceGone, match="cam2: .*nope.avi does not exist"):
        cam2.open()


def test_opencv_wrong_size_and_bad_exposure(image_sequence):
    with OpenCVCamera(image_sequence, name="c", width=W * 2, height=H, exposure_control=False) as cam:
        with pytest.raises(DeviceError, match=r"delivers 32x24 frames, the config asks for 64x24"):
            cam.capture(0.01)
        with pytest.raises(InputError, match="exposure_s must be a positive"):
            cam.capture(-1.0)
        info = cam.check()
    assert not info.ok and "32x24" in info.detail


def test_expand_braces():
    assert expand_braces("*.{exr,png}") == ["*.exr", "*.png"]
    assert expand_braces("a{1,2}b{x,y}") == ["a1bx", "a1by", "a2bx", "a2by"]
    assert expand_braces("plain") == ["plain"]


# --------------------------------------------------------------------------- tethered folder


def test_directory_camera_waits_for_a_complete_file(tmp_path):
    """A writer thread writes half an EXR, waits until the camera has seen the partial file
    and failed to read it, then finishes: the camera returns the complete image."""
    rng = np.random.default_rng(0)
    truth = rng.random((H, W, 3), dtype=np.float32) * 4.0
    ref = tmp_path / "ref.exr"
    write_exr(ref, truth)
    blob = ref.read_bytes()
    shots = tmp_path / "shots"
    shots.mkdir()
    saw_partial = threading.Event()
    states = []

    def on_wait(state, path, size):
        states.append((state, size))
        if state == "unreadable":
            saw_partial.set()

    def writer():
        with open(shots / "IMG_0001.exr", "wb") as f:
            f.write(blob[: len(blob) // 2])
            f.flush()
            assert saw_partial.wait(10)
            f.write(blob[len(blob) // 2 :])

    threads = []

    def trigger(exposure_s):
        t = threading.Thread(target=writer)
        t.start()
        threads.append(t)

    cam = DirectoryCamera(shots, name="dslr", trigger=trigger, settle_s=0.05, timeout_s=10, on_wait=on_wait)
    assert isinstance(cam, CameraDevice)
    img = cam.capture(1 / 125)
    threads[0].join()
    np.testing.assert_array_equal(img, truth)
    assert cam.last_path == shots / "IMG_0001.exr" and cam.last_exposure_s == 1 / 125
    seq = [s for s, _ in states if s != "waiting"]
    assert seq.index("unreadable") < seq.index("done")
    assert ("unreadable", len(blob) // 2) in states and states[-1] == ("done", len(blob))


def test_directory_camera_jpeg_without_eoi_is_not_read(tmp_path):
    ok, buf = cv2.imencode(".jpg", frame_bgr(1), [cv2.IMWRITE_JPEG_QUALITY, 95])
    blob = buf.tobytes()
    assert blob[-2:] == b"\xff\xd9"
    seen = threading.Event()

    def writer():
        with open(tmp_path / "a.JPG", "wb") as f:
            f.write(blob[:-2])  # everything but the end-of-image marker: decodable, but incomplete
            f.flush()
            assert seen.wait(10)
            f.write(blob[-2:])

    t = threading.Thread(target=writer)
    cam = DirectoryCamera(
        tmp_path,
        name="c",
        trigger=lambda e: t.start(),
        settle_s=0.05,
        timeout_s=10,
        on_wait=lambda s, p, n: seen.set() if s == "unreadable" else None,
    )
    img = cam.capture(0.01)
    t.join()
    expected = srgb_decode(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1] / np.float32(255))
    np.testing.assert_allclose(img, expected, atol=1e-6)


def test_directory_camera_ignores_existing_and_hidden_files(tmp_path):
    write_png(tmp_path / "old.png", np.zeros((H, W, 3), np.float32))
    new = np.random.default_rng(1).random((H, W, 3)).astype(np.float32)

    def trigger(exposure_s):
        (tmp_path / ".tmp-partial.png").write_bytes(b"not an image")
        (tmp_path / "notes.txt").write_text("not matching the pattern")
        threading.Thread(target=write_png, args=(tmp_path / "new.png", new)).start()

    cam = DirectoryCamera(
        tmp_path, name="c", pattern="*.png", trigger=trigger, settle_s=0.02, timeout_s=10, width=W, height=H
    )
    img = cam.capture(0.5)
    assert cam.last_path.name == "new.png"
    np.testing.assert_array_equal(img, read_png(tmp_path / "new.png"))
    np.testing.assert_allclose(img, new, atol=0.01)  # 8-bit sRGB quantisation


def test_directory_camera_trigger_command_substitutes_exposure(tmp_path):
    src = tmp_path / "src.png"
    write_png(src, np.full((H, W, 3), 0.25, np.float32))
    shots = tmp_path / "shots"
    shots.mkdir()
    cmd = [
        sys.executable,
        "-c",
        "import shutil,sys; shutil.copy(sys.argv[1], sys.argv[2] + '/shot_' + sys.argv[3] + '.png')",
        str(src),
        "{folder}",
        "{exposure_s}",
    ]
    cam = DirectoryCamera(shots, name="c", trigger=cmd, settle_s=0.02, timeout_s=20)
    img = cam.capture(0.004)
    assert cam.last_path.name == "shot_0.004.png"
    np.testing.assert_allclose(img, 0.25, atol=0.003)
    bad = DirectoryCamera(
        shots, name="c", trigger=[sys.executable, "-c", "import sys; sys.exit('no camera found')"], timeout_s=20
    )
    with pytest.raises(DeviceError, match=r"trigger command .* failed with exit code 1: no camera found"):
        bad.capture(0.01)


def test_directory_camera_timeouts_and_errors_name_the_folder(tmp_path):
    cam = DirectoryCamera(tmp_path, name="dslr", timeout_s=0.2, settle_s=0.01)
    with pytest.raises(
        DeviceTimeout,
        match=rf"camera dslr: no new image matching .* appeared in {tmp_path} within "
        r"0.2 s — is the tethering software running",
    ):
        cam.capture(0.01)
    # a file that appears but never becomes readable
    cam = DirectoryCamera(
        tmp_path,
        name="dslr",
        timeout_s=0.3,
        settle_s=0.01,
        trigger=lambda e: (tmp_path / "broken.exr").write_bytes(b"garbage"),
    )
    with pytest.raises(DeviceTimeout, match="broken.exr .* did not become a complete, readable image"):
        cam.capture(0.01)
    missing = DirectoryCamera(tmp_path / "nope", name="dslr")
    with pytest.raises(DeviceGone, match="folder .*nope does not exist"):
        missing.capture(0.01)
    assert not missing.check().ok and cam.check().ok
    sized = DirectoryCamera(
        tmp_path,
        name="dslr",
        width=W + 1,
        height=H,
        settle_s=0.01,
        timeout_s=10,
        trigger=lambda e: write_png(tmp_path / "x.png", np.zeros((H, W, 3), np.float32)),
    )
    with pytest.raises(DeviceError, match=r"x.png is 32x24, the config asks for 33x24"):
        sized.capture(0.01)
