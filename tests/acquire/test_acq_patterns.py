"""Backdrop patterns: complements, contrast, determinism, natural-image spectra, saved bytes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.acquire.patterns import (
    check_saved_patterns,
    complement,
    natural_image,
    plan_patterns,
    random_pattern,
    save_patterns,
)
from opacityhull.errors import InputError
from opacityhull.riggeometry import RigGeometry

from rigkit import GEOMETRY
from test_acq_plan import _plan


@settings(max_examples=25, deadline=None)
@given(w=st.integers(1, 40), h=st.integers(1, 40), cell=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_random_pattern_and_complement_differ_everywhere(w, h, cell, seed):
    p = random_pattern(np.random.default_rng(seed), width=w, height=h, cell_px=cell)
    assert p.shape == (h, w, 3) and p.dtype == np.uint8
    c = complement(p)
    assert np.array_equal(p.astype(int) + c.astype(int), np.full((h, w, 3), 255))
    # |B1 - B2| >= 129 per channel at every pixel: matting is well conditioned everywhere
    assert np.abs(p.astype(int) - c.astype(int)).min() >= 129
    # cells are constant
    cells = p[::cell, ::cell]
    up = np.repeat(np.repeat(cells, cell, 0), cell, 1)[:h, :w]
    assert np.array_equal(up, p)


def test_random_pattern_statistics():
    p = random_pattern(np.random.default_rng(0), width=256, height=256, cell_px=1).astype(int)
    # both halves of the range are used about equally, per channel
    for ch in range(3):
        frac_high = np.mean(p[..., ch] >= 192)
        assert 0.47 < frac_high < 0.53
    assert np.all((p < 64) | (p >= 192))
    with pytest.raises(InputError):
        random_pattern(np.random.default_rng(0), width=0, height=3)
    with pytest.raises(InputError):
        complement(np.zeros((2, 2, 3), np.float32))


def test_natural_image_has_one_over_f_spectrum():
    img = natural_image(np.random.default_rng(3), width=128, height=128).astype(np.float64).mean(axis=-1)
    F = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(128)[:, None]
    fx = np.fft.fftfreq(128)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    bins = np.logspace(np.log10(2 / 128), np.log10(0.35), 12)
    k = np.digitize(f, bins)
    pw = [F[k == i].mean() for i in range(1, len(bins))]
    fc = [np.sqrt(bins[i - 1] * bins[i]) for i in range(1, len(bins))]
    slope = np.polyfit(np.log(fc), np.log(pw), 1)[0]
    # power ~ 1/f^2 for amplitude 1/f (clipping at the percentiles flattens it a little)
    assert -2.4 < slope < -1.6, slope


def test_plan_patterns_deterministic_per_display(tmp_path):
    geo = RigGeometry.from_dict(GEOMETRY)
    plan = _plan()
    a = plan_patterns(plan, geo)
    b = plan_patterns(plan, geo)
    assert sorted(a) == [1, 2, 3, 4]
    for pid in a:
        for d in ("bottom", "back"):
            assert np.array_equal(a[pid].images[d], b[pid].images[d])
    assert a[1].images["bottom"].shape == (16, 16, 3) and a[1].images["back"].shape == (12, 16, 3)
    assert not np.array_equal(a[1].images["bottom"][:12], a[1].images["back"])
    assert not np.array_equal(a[1].images["bottom"], a[3].images["bottom"])
    other = plan_patterns(_plan(lambda d: d["phases"]["matting"].__setitem__("seed", 99)), geo)
    assert not np.array_equal(other[1].images["bottom"], a[1].images["bottom"])
    table = save_patterns(tmp_path, a)
    assert table["p002"]["of"] == 1 and table["p001"]["kind"] == "random"
    assert check_saved_patterns(tmp_path, a) == []
    (tmp_path / "patterns" / "back" / "p003.png").write_bytes(b"garbage")
    assert check_saved_patterns(tmp_path, a) == ["patterns/back/p003.png"]


def test_envmatte_images_from_files(tmp_path):
    import cv2

    src = (np.random.default_rng(1).random((40, 50, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "n.png"), src)
    geo = RigGeometry.from_dict(GEOMETRY)
    from opacityhull.acquire.plan import parse_plan

    plan = parse_plan({"plan": {"name": "e"}, "phases": {"envmatte": {"images": ["n.png"]}}}, base_dir=tmp_path)
    pats = plan_patterns(plan, geo)
    names = [d.name for d in geo.displays]
    # one illumination domain per display: id 1 + i lights display i only, black elsewhere
    assert list(pats) == list(range(1, len(names) + 1)) and all(p.kind == "natural" for p in pats.values())
    for i, name in enumerate(names):
        p = pats[1 + i]
        assert p.source.startswith(f"{name}:user:")
        for d in geo.displays:
            img = p.images[d.name]
            assert img.shape == (d.resolution[1], d.resolution[0], 3)
            if d.name == name:
                want = cv2.resize(src, d.resolution, interpolation=cv2.INTER_AREA)[:, :, ::-1]
                assert np.array_equal(img, want)
            else:
                assert not img.any()


def test_natural_sources_mix_probes_noise_and_user_images(tmp_path):
    import cv2

    from opacityhull.acquire.plan import parse_plan

    src = (np.random.default_rng(2).random((20, 30, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "u.png"), src)
    geo = RigGeometry.from_dict(GEOMETRY)
    name = geo.displays[0].name
    plan = parse_plan(
        {
            "plan": {"name": "e"},
            "phases": {
                "natural": {
                    "images": 6,
                    "kernels": 4,
                    "sources": ["user", "probes", "noise"],
                    "user_images": ["u.png"],
                    "displays": [name],
                }
            },
        },
        base_dir=tmp_path,
    )
    pats = plan_patterns(plan, geo)
    assert sorted(pats) == list(range(1, 7))
    kinds = [pats[k].source.split(":")[1] for k in sorted(pats)]
    assert kinds == ["user", "probe", "noise", "probe", "noise", "probe"]
    for k, p in pats.items():
        img = p.images[name]
        assert img.dtype == np.uint8 and img.any()
        if kinds[k - 1] == "probe":
            # exposed to a mean of 0.4 of white, then clipped: the mean can only drop
            assert 0.1 < img.mean() / 255 <= 0.41
    # deterministic from the plan seed
    again = plan_patterns(plan, geo)
    assert all(np.array_equal(pats[k].images[name], again[k].images[name]) for k in pats)
