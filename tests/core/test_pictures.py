"""pictures.py: sRGB 8-bit, contact sheets (labels, headers, colour bar), animations.

The GIF frame delay is read back two ways: Pillow's decoder, and our own walk over the
file's Graphic Control Extension blocks (GIF89a), so a writer passing seconds where
milliseconds are expected (the relit-orbit 0 ms delay bug) cannot pass.
"""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.errors import InputError
from opacityhull.imageio import read_png, srgb_encode
from opacityhull.pictures import ColorBar, contact_sheet, encoded_to_u8, heat, to_srgb8, write_animation, write_sheet


def gif_frame_delays_cs(data: bytes) -> list[int]:
    """Frame delays (centiseconds) from a GIF's Graphic Control Extensions, walking the
    block structure (GIF89a spec, sections 18-23) without an image library."""
    assert data[:6] in (b"GIF87a", b"GIF89a")
    pos = 13
    flags = data[10]
    if flags & 0x80:
        pos += 3 * (2 ** ((flags & 7) + 1))
    delays = []
    while pos < len(data):
        b = data[pos]
        if b == 0x3B:  # trailer
            break
        if b == 0x21:  # extension: label, then sub-blocks
            label = data[pos + 1]
            pos += 2
            if label == 0xF9:
                delays.append(int.from_bytes(data[pos + 2 : pos + 4], "little"))
            while data[pos] != 0:
                pos += data[pos] + 1
            pos += 1
        elif b == 0x2C:  # image descriptor, optional local table, LZW data sub-blocks
            lflags = data[pos + 9]
            pos += 10
            if lflags & 0x80:
                pos += 3 * (2 ** ((lflags & 7) + 1))
            pos += 1
            while data[pos] != 0:
                pos += data[pos] + 1
            pos += 1
        else:
            raise AssertionError(f"unexpected GIF block 0x{b:02x} at byte {pos}")
    return delays


def _frames(n=5, h=12, w=16):
    rng = np.random.default_rng(1)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("fps,cs", [(12.0, 8), (10.0, 10), (25.0, 4), (2.0, 50)])
def test_gif_frame_delay_read_back(tmp_path, fps, cs):
    from PIL import Image

    p = write_animation(tmp_path / "a.gif", _frames(), fps=fps)
    assert gif_frame_delays_cs(p.read_bytes()) == [cs] * 5
    with Image.open(p) as im:
        assert im.n_frames == 5
        assert im.info["loop"] == 0
        for k in range(5):
            im.seek(k)
            assert im.info["duration"] == 10 * cs


def test_gif_identical_frames_keep_the_playing_time(tmp_path):
    """Pillow merges repeated frames into one with the summed delay: same playback."""
    f, g = _frames(2)
    p = write_animation(tmp_path / "same.gif", [f, f, f, g], fps=10)
    assert sum(gif_frame_delays_cs(p.read_bytes())) == 40


def test_relight_orbit_gif_has_the_requested_delay(tmp_path):
    """The relit orbit writes through the same writer: 12 fps → 8 cs, not 0 (the old seconds-for-ms bug)."""
    from opacityhull.relight.runner import write_gif

    write_gif(tmp_path / "orbit.gif", [np.full((8, 8, 3), v, np.float32) for v in (0.1, 0.5, 0.9)], fps=12.0)
    assert gif_frame_delays_cs((tmp_path / "orbit.gif").read_bytes()) == [8, 8, 8]


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_animation_bad_fps(tmp_path, bad):
    with pytest.raises(InputError, match="fps"):
        write_animation(tmp_path / "a.gif", _frames(2), fps=bad)
    assert not list(tmp_path.iterdir())


def test_animation_bad_input(tmp_path):
    with pytest.raises(InputError, match="no frames"):
        write_animation(tmp_path / "a.gif", [], fps=10)
    with pytest.raises(InputError, match="different sizes"):
        write_animation(tmp_path / "a.gif", [_frames(1)[0], _frames(1, h=5)[0]], fps=10)
    with pytest.raises(InputError, match="suffix"):
        write_animation(tmp_path / "a.avi", _frames(2), fps=10)
    with pytest.raises(InputError, match="uint8"):
        write_animation(tmp_path / "a.gif", [np.zeros((4, 4, 3), np.float32)], fps=10)
    assert not list(tmp_path.iterdir())


def test_to_srgb8_matches_encoder():
    x = np.linspace(-0.5, 1.5, 64, dtype=np.float32).reshape(4, 4, 4)
    x[0, 0, 0] = np.nan
    out = to_srgb8(x, exposure=0.5)
    ref = np.round(srgb_encode(np.clip(np.nan_to_num(x[..., :3] * 0.5), 0, 1)) * 255).astype(np.uint8)
    assert out.dtype == np.uint8 and out.shape == (4, 4, 3)
    np.testing.assert_array_equal(out, ref)
    # 18 % grey encodes to 118 (IEC 61966-2-1)
    assert to_srgb8(np.full((1, 1, 3), 0.18, np.float32))[0, 0, 0] == 118


def test_heat_endpoints_match_matplotlib():
    import matplotlib

    h = heat(np.array([[0.0, 2.0, np.nan, 9.0]]), vmin=0.0, vmax=2.0)
    cm = matplotlib.colormaps["inferno"]
    np.testing.assert_array_equal(h[0, 0], np.round(np.asarray(cm(0.0)[:3]) * 255).astype(np.uint8))
    np.testing.assert_array_equal(h[0, 1], np.round(np.asarray(cm(1.0)[:3]) * 255).astype(np.uint8))
    np.testing.assert_array_equal(h[0, 2], h[0, 0])  # NaN → vmin
    np.testing.assert_array_equal(h[0, 3], h[0, 1])  # clipped
    with pytest.raises(InputError, match="vmin"):
        heat(np.zeros((2, 2)), vmin=1.0, vmax=1.0)


def test_contact_sheet_layout_exact():
    """Unlabelled tiles land at gap + k * (cell + gap), and the gaps hold the background."""
    tiles = [np.full((4, 6, 3), 10 * (i + 1), np.uint8) for i in range(5)]
    s = contact_sheet(tiles, columns=3, gap=2, background=7)
    assert s.shape == (2 * (4 + 2) + 2, 3 * (6 + 2) + 2, 3) and s.dtype == np.uint8
    for i in range(5):
        r, c = divmod(i, 3)
        y, x = 2 + r * 6, 2 + c * 8
        assert (s[y : y + 4, x : x + 6] == 10 * (i + 1)).all()
    assert (s[:2] == 7).all() and (s[:, :2] == 7).all()
    assert (s[8:12, 18:24] == 7).all()  # the empty sixth cell


def test_contact_sheet_labels_headers_colorbar():
    tiles = [np.full((40, 60, 3), 200, np.uint8) for _ in range(6)]
    plain = contact_sheet(tiles, columns=3)
    lab = contact_sheet(tiles, columns=3, labels=["a", "", "c", "", "", ""])
    assert lab.shape == plain.shape
    assert (lab[2:8, 2:62] != 200).any()  # band darkened / text drawn on tile 0
    np.testing.assert_array_equal(lab[2:42, 64:124], plain[2:42, 64:124])  # tile 1 unlabelled
    full = contact_sheet(
        tiles,
        columns=3,
        headers=["photo", "render", "error"],
        colorbar=ColorBar(cmap="inferno", vmin=0.0, vmax=0.25, label="|d| x4"),
    )
    assert full.shape[1] == plain.shape[1] and full.shape[0] > plain.shape[0] + 20
    top = full.shape[0] - plain.shape[0]
    # the header strip carries white text over each column
    hdr = full[: top - 20]
    for c in range(3):
        assert hdr[:, 2 + c * 62 : 62 + c * 62].max() > 200
    # the colour bar ramps from inferno(0) to inferno(1) across the bottom strip
    import matplotlib

    row = next(
        y for y in range(full.shape[0] - 1, 0, -1) if (full[y, 6] == heat(np.zeros((1, 1)), vmax=1.0)[0, 0]).all()
    )
    right = full[row, full.shape[1] - 7]
    np.testing.assert_array_equal(right, np.round(np.asarray(matplotlib.colormaps["inferno"](1.0)[:3]) * 255))


def test_contact_sheet_scaling_and_errors():
    t = np.arange(12, dtype=np.uint8).reshape(3, 4)
    s = contact_sheet([t], min_width=10, gap=0)
    assert s.shape == (9, 12, 3)  # integer factor 3, nearest
    np.testing.assert_array_equal(s[::3, ::3, 0], t)
    big = contact_sheet([np.zeros((50, 100, 3), np.uint8)], max_width=25, gap=0)
    assert big.shape == (12, 25, 3) or big.shape == (13, 25, 3)
    with pytest.raises(InputError, match="no tiles"):
        contact_sheet([])
    with pytest.raises(InputError, match="uint8"):
        contact_sheet([np.zeros((2, 2, 3), np.float32)])
    with pytest.raises(InputError, match="labels"):
        contact_sheet([t, t], labels=["x"])


def test_write_sheet_roundtrip(tmp_path):
    s = encoded_to_u8(np.linspace(0, 1, 30).reshape(2, 5, 3))
    p = write_sheet(tmp_path / "s.png", s)
    import cv2

    np.testing.assert_array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[..., ::-1], s)
    np.testing.assert_array_equal(np.round(read_png(p, linear=True)[..., :3] * 255).astype(np.uint8), s)
    with pytest.raises(InputError, match="uint8"):
        write_sheet(tmp_path / "f.png", s.astype(np.float32))
