"""Image IO round trips, half-float clamping, sRGB, atomic writes."""

import warnings

import numpy as np
import pytest

from opacityhull.errors import FormatError, InputError, ShapeError
from opacityhull.imageio import (
    HALF_MAX,
    HalfOverflowWarning,
    atomic_path,
    read_exr,
    read_exr_layers,
    read_hdr,
    read_image,
    read_png,
    srgb_decode,
    srgb_encode,
    write_exr,
    write_exr_layers,
    write_hdr,
    write_image,
    write_png,
)

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_exr_float32_roundtrip_is_exact(tmp_path, channels):
    img = RNG.normal(size=(9, 13, channels)).astype(np.float32) * 1e6
    img[0, 0, 0] = np.nan
    write_exr(tmp_path / "a.exr", img)
    back = read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and back.shape == img.shape
    np.testing.assert_array_equal(back, img)


def test_exr_half_clamps_with_warning_naming_file(tmp_path):
    img = np.array([[[1.0, 70000.0, -1e9]]], dtype=np.float32)
    with pytest.warns(HalfOverflowWarning, match=r"h\.exr.*clamped"):
        write_exr(tmp_path / "h.exr", img, half=True)
    back = read_exr(tmp_path / "h.exr")
    assert np.all(np.isfinite(back))
    np.testing.assert_array_equal(back[0, 0], [1.0, HALF_MAX, -HALF_MAX])


def test_exr_half_without_overflow_is_silent(tmp_path):
    img = RNG.uniform(0, 60000, (4, 4, 3)).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_exr(tmp_path / "h.exr", img, half=True)
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr"), img, rtol=1e-3)


def test_exr_noncontiguous_input_written_correctly(tmp_path):
    # PITFALLS: a strided slice was written as wrong data by OpenEXR
    big = RNG.random((10, 12, 4)).astype(np.float32)
    view = big[::2, 1::2, :3]
    write_exr(tmp_path / "s.exr", view)
    np.testing.assert_array_equal(read_exr(tmp_path / "s.exr"), view)


def test_exr_layers_roundtrip(tmp_path):
    layers = {
        "a000p000_l0": RNG.random((5, 6, 3)).astype(np.float32),
        "a045p000_l1": RNG.random((5, 6, 3)).astype(np.float32),
    }
    write_exr_layers(tmp_path / "r.exr", layers)
    back = read_exr_layers(tmp_path / "r.exr")
    assert set(back) == set(layers)
    for k in layers:
        np.testing.assert_array_equal(back[k], layers[k])
    with pytest.raises(InputError, match="must not contain"):
        write_exr_layers(tmp_path / "x.exr", {"a.b": layers["a000p000_l0"]})


def test_hdr_roundtrip_within_rgbe_precision(tmp_path):
    img = RNG.uniform(0.01, 1e5, (8, 8, 3)).astype(np.float32)
    img[:] = img[..., :1]  # grey: RGBE's shared exponent then keeps ~1% relative precision
    write_hdr(tmp_path / "a.hdr", img)
    np.testing.assert_allclose(read_hdr(tmp_path / "a.hdr"), img, rtol=0.01)
    with pytest.raises(InputError, match="negative"):
        write_hdr(tmp_path / "b.hdr", -img)


def test_hdr_reads_shared_probe():
    from opacityhull.data import probe_path

    env = read_hdr(probe_path("grace"))
    assert env.shape == (128, 256, 3) and env.dtype == np.float32
    assert np.all(np.isfinite(env)) and env.min() >= 0
    # real HDR: the brightest texel is far above the median
    assert env.max() / np.median(env) > 1e4  # grace: a sun ~1e5x the median


@pytest.mark.parametrize("bits", [8, 16])
def test_png_srgb_roundtrip(tmp_path, bits):
    img = RNG.random((7, 5, 3)).astype(np.float32)
    write_png(tmp_path / "a.png", img, bits=bits)
    back = read_png(tmp_path / "a.png")
    tol = 0.01 if bits == 8 else 1e-4
    np.testing.assert_allclose(back, img, atol=tol)


def test_png_alpha_not_encoded(tmp_path):
    img = np.zeros((2, 2, 4), np.float32)
    img[..., 3] = 0.5
    img[..., :3] = 0.5
    write_png(tmp_path / "a.png", img, bits=16)
    back = read_png(tmp_path / "a.png", linear=True)
    np.testing.assert_allclose(back[..., 3], 0.5, atol=1e-4)
    np.testing.assert_allclose(back[..., 0], srgb_encode(np.float32(0.5)), atol=1e-4)


def test_srgb_encode_decode_inverse_and_monotone():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-6)
    assert np.all(np.diff(srgb_encode(x)) >= 0)


def test_dispatch_and_errors(tmp_path):
    img = RNG.random((3, 3, 3)).astype(np.float32)
    write_image(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), img)
    with pytest.raises(InputError, match=r"\.bmp"):
        write_image(tmp_path / "a.bmp", img)
    with pytest.raises(ShapeError, match=r"expected \(H, W\)"):
        write_exr(tmp_path / "b.exr", np.zeros((2, 2, 5)))
    (tmp_path / "t.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    with pytest.raises(FormatError, match="t.exr"):
        read_exr(tmp_path / "t.exr")
    with pytest.raises(FormatError, match="not found"):
        read_exr(tmp_path / "missing.exr")


def test_atomic_path_leaves_old_file_on_error(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("new, half written")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.txt"]
