"""The differentiable EWA surfel rasterizer: forward against its NumPy reference, every
gradient against central finite differences of the float64 reference, degenerate surfels
stay finite, and the results are the same bytes whatever the thread count or tile size."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from opacityhull.errors import InputError, ShapeError
from opacityhull.optimize.raster import (
    RasterCamera,
    RasterConfig,
    SplatParams,
    rasterize,
    rasterize_backward,
)
from opacityhull.optimize.raster_reference import rasterize_reference

W, H = 24, 20
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors")
DEGENERATE = (
    "edge_on",
    "tiny",
    "zero_scale",
    "opaque",
    "transparent",
    "behind",
    "near",
    "coincident",
    "outside",
    "zero_quat",
)
# no threshold anywhere near the fragments: the image is a smooth function of the parameters
SMOOTH = RasterConfig(alpha_min=0.0, transmittance_min=0.0, cutoff_sigma=9.0, background=(0.2, 0.5, 0.9))


def look_at_camera(eye, target=(0.0, 0.0, 0.0), *, f=30.0, width=W, height=H, pp=(0.0, 0.0), skew=0.0) -> RasterCamera:
    eye = np.asarray(eye, np.float64)
    fwd = np.asarray(target, np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    up = np.array([0.0, 1.0, 0.0]) if abs(fwd[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world
    K = np.array([[f, skew, (width - 1) / 2 + pp[0]], [0.0, f * 1.07, (height - 1) / 2 + pp[1]], [0.0, 0.0, 1.0]])
    return RasterCamera(K=K, cam_from_world=np.hstack([R, (-R @ eye)[:, None]]), width=width, height=height)


def random_scene(seed: int, n: int, cam: RasterCamera, degenerate: tuple[str, ...] = ()) -> SplatParams:
    """n surfels in a ball around the origin seen by ``cam``, with the listed degenerate
    ones appended (each kind once)."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.6, 0.6, (n, 3))
    quats = rng.normal(size=(n, 4))
    log_scales = rng.uniform(-3.2, -1.6, (n, 2))
    logits = rng.uniform(-1.5, 2.5, n)
    colors = rng.uniform(0.0, 1.0, (n, 3))
    Rcw, tcw = cam.cam_from_world[:, :3], cam.cam_from_world[:, 3]
    eye = -Rcw.T @ tcw
    extra = []
    for kind in degenerate:
        m = rng.uniform(-0.3, 0.3, 3)
        q = rng.normal(size=4)
        ls = rng.uniform(-3.0, -2.0, 2)
        lg = rng.uniform(-1.0, 2.0)
        if kind == "edge_on":  # normal perpendicular to the ray through the centre
            v = m - eye
            v /= np.linalg.norm(v)
            a = np.cross(v, rng.normal(size=3))
            a /= np.linalg.norm(a)
            R = np.stack([v, a, np.cross(v, a)], axis=1)
            q = Rotation.from_matrix(R).as_quat(scalar_first=True)
            ls = np.array([-1.5, -3.0])
        elif kind == "tiny":
            ls = np.array([-12.0, -9.0])
        elif kind == "zero_scale":
            ls = np.array([-800.0, -800.0])  # exp underflows to exactly 0
        elif kind == "opaque":
            lg = 30.0
        elif kind == "transparent":
            lg = -30.0
        elif kind == "behind":
            m = eye - 0.5 * (Rcw[2] + 0.3 * Rcw[0])
        elif kind == "near":  # centre just in front of near_m, disc reaching behind the camera
            m = eye + 0.0101 * Rcw[2] + 0.002 * Rcw[0]
            ls = np.array([-2.0, -2.5])
        elif kind == "coincident":  # two identical surfels (same depth: the index breaks the tie)
            extra.append((m, q, ls, lg, rng.uniform(0.0, 1.0, 3)))
        elif kind == "outside":
            m = eye + 2.0 * Rcw[2] + 9.0 * Rcw[0]
        elif kind == "zero_quat":
            q = np.zeros(4)
        extra.append((m, q, ls, lg, rng.uniform(0.0, 1.0, 3)))
    if extra:
        means = np.concatenate([means, [e[0] for e in extra]])
        quats = np.concatenate([quats, [e[1] for e in extra]])
        log_scales = np.concatenate([log_scales, [e[2] for e in extra]])
        logits = np.concatenate([logits, [e[3] for e in extra]])
        colors = np.concatenate([colors, [e[4] for e in extra]])
    f32 = np.float32
    return SplatParams(
        means=means.astype(f32),
        quats=quats.astype(f32),
        log_scales=log_scales.astype(f32),
        opacity_logits=logits.astype(f32),
        colors=colors.astype(f32),
    )


cameras = st.builds(
    lambda az, el, dist, f, px, py, skew: look_at_camera(
        (dist * np.cos(el) * np.sin(az), dist * np.sin(el), dist * np.cos(el) * np.cos(az)), f=f, pp=(px, py), skew=skew
    ),
    st.floats(-np.pi, np.pi),
    st.floats(-1.2, 1.2),
    st.floats(1.6, 4.0),
    st.floats(14.0, 45.0),
    st.floats(-3.0, 3.0),
    st.floats(-3.0, 3.0),
    st.sampled_from([0.0, 0.0, 1.5]),
)
degenerate_sets = st.lists(st.sampled_from(DEGENERATE), max_size=4, unique=True).map(tuple)


def _loss_weights(seed: int):
    rng = np.random.default_rng(seed + 7)
    return rng.normal(size=(H, W, 3)), rng.normal(size=(H, W))


def _f64(p: SplatParams) -> dict[str, np.ndarray]:
    return {k: np.asarray(getattr(p, k), np.float64) for k in FIELDS}


def _assert_finite(out, g) -> None:
    for a in (out.image, out.alpha, out.depth):
        assert np.all(np.isfinite(a))
    for k in (*FIELDS, "means2d_abs"):
        assert np.all(np.isfinite(getattr(g, k))), k


def check_gradients(p: SplatParams, cam: RasterCamera, cfg: RasterConfig, seed: int, *, h: float = 1e-6) -> float:
    """Every analytic gradient against central differences of the float64 reference on
    L = Σ wi·image + Σ wa·alpha. A coordinate whose one-sided differences disagree sits
    on a threshold (cutoff, alpha_min, the 0.99 clamp, a depth-order swap, near_m) and is
    skipped. Returns the fraction of coordinates checked."""
    wi, wa = _loss_weights(seed)
    out = rasterize(p, cam, config=cfg)
    g = rasterize_backward(out, p, cam, dL_dimage=wi, dL_dalpha=wa, config=cfg)
    _assert_finite(out, g)
    base = _f64(p)

    def loss(field: str, arr: np.ndarray) -> float:
        img, alpha, _ = rasterize_reference(SplatParams(**{**base, field: arr}), cam, config=cfg)
        return float((img * wi).sum() + (alpha * wa).sum())

    f0 = loss("means", base["means"])
    checked = total = 0
    for field in FIELDS:
        arr = base[field]
        an = np.asarray(getattr(g, field), np.float64)
        fd = np.full(arr.shape, np.nan)
        for idx in np.ndindex(arr.shape):
            up, dn = arr.copy(), arr.copy()
            up[idx] += h
            dn[idx] -= h
            fp, fm = loss(field, up), loss(field, dn)
            central = (fp - fm) / (2 * h)
            total += 1
            if abs((fp - f0) / h - (f0 - fm) / h) > 1e-3 * max(1.0, abs(central)):
                continue
            fd[idx] = central
        ok = np.isfinite(fd)
        checked += int(ok.sum())
        scale = 1.0 + np.max(np.abs(fd[ok]), initial=0.0)
        err = np.abs(an[ok] - fd[ok])
        assert np.all(err <= 2e-4 * scale + 1e-3 * np.abs(fd[ok])), (
            field,
            np.max(err),
            scale,
            an[ok][np.argmax(err)],
            fd[ok][np.argmax(err)],
        )
    return checked / total


# ------------------------------------------------------------------------ forward


@settings(max_examples=40, deadline=None)
@given(
    cam=cameras,
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 30),
    degenerate=degenerate_sets,
    bg=st.sampled_from([(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.2, 0.5, 0.9)]),
)
def test_forward_equals_numpy_reference(cam, seed, n, degenerate, bg):
    p = random_scene(seed, n, cam, degenerate)
    cfg = RasterConfig(background=bg)
    out = rasterize(p, cam, config=cfg)
    img, alpha, depth = rasterize_reference(p, cam, config=cfg)
    assert out.image.dtype == np.float32 and out.image.shape == (H, W, 3)
    np.testing.assert_allclose(out.image, img, atol=1e-5)
    np.testing.assert_allclose(out.alpha, alpha, atol=1e-5)
    np.testing.assert_allclose(out.depth, depth, atol=1e-5 * max(1.0, float(np.max(depth))))


@settings(max_examples=15, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31 - 1), tile=st.sampled_from([1, 5, 8, 32]))
def test_tile_size_does_not_change_the_image(cam, seed, tile):
    """Each tile holds its surfels in the same depth order, so every pixel sees the same
    fragments in the same order: the same bytes whatever the tiling."""
    p = random_scene(seed, 25, cam, ("coincident",))
    a = rasterize(p, cam)
    b = rasterize(p, cam, config=RasterConfig(tile_px=tile))
    assert a.image.tobytes() == b.image.tobytes() and a.alpha.tobytes() == b.alpha.tobytes()
    assert a.n_fragments == b.n_fragments


def test_culling_and_fragment_count():
    cam = look_at_camera((0.0, 0.0, 3.0))
    p = random_scene(3, 4, cam, ("behind", "outside", "near"))
    out = rasterize(p, cam)
    assert out.visible.tolist()[4:] == [False, False, True]
    # a lone opaque surfel facing the camera: n_fragments counts its composited pixels
    one = SplatParams(
        means=np.zeros((1, 3), np.float32),
        quats=np.array([[1, 0, 0, 0]], np.float32),
        log_scales=np.log(np.full((1, 2), 0.05, np.float32)),
        opacity_logits=np.array([2.0], np.float32),
        colors=np.ones((1, 3), np.float32),
    )
    out = rasterize(one, cam)
    assert out.n_fragments == int(np.count_nonzero(out.alpha > 0)) > 0
    np.testing.assert_allclose(out.depth, 3.0 * out.alpha, rtol=1e-6)


# ------------------------------------------------------------------------ backward


@settings(max_examples=20, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6))
def test_gradients_equal_finite_differences(cam, seed, n):
    p = random_scene(seed, n, cam)
    frac = check_gradients(p, cam, SMOOTH, seed)
    assert frac > 0.97


@settings(max_examples=20, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31 - 1), n=st.integers(0, 4), degenerate=degenerate_sets)
def test_gradients_with_degenerate_surfels(cam, seed, n, degenerate):
    """Default thresholds and degenerate surfels: every coordinate away from a threshold
    matches its finite difference, and nothing is NaN or Inf."""
    p = random_scene(seed, n, cam, degenerate)
    if p.n == 0:
        return
    frac = check_gradients(p, cam, RasterConfig(background=(0.2, 0.5, 0.9)), seed)
    assert frac > 0.5


@pytest.mark.parametrize("kind", DEGENERATE)
def test_each_degenerate_kind_is_finite_and_differentiable(kind):
    cam = look_at_camera((0.4, -0.3, 2.5))
    p = random_scene(11, 3, cam, (kind,))
    frac = check_gradients(p, cam, SMOOTH, 11)
    assert frac > 0.8


def test_backward_alpha_only_and_colour_gradient_is_exact():
    """dL/dcolour is the compositing weight alpha_i T_i: with dL/dimage = 1 on one channel
    and a single surfel it equals that surfel's alpha image summed."""
    cam = look_at_camera((0.0, 0.0, 3.0))
    p = random_scene(5, 1, cam)
    out = rasterize(p, cam)
    d = np.zeros((H, W, 3))
    d[..., 1] = 1.0
    g = rasterize_backward(out, p, cam, dL_dimage=d, dL_dalpha=None)
    assert g.colors[0, 1] == pytest.approx(float(out.alpha.astype(np.float64).sum()), rel=1e-5)
    assert g.colors[0, 0] == 0.0 and g.colors[0, 2] == 0.0


# ------------------------------------------------------------------------ determinism and errors


def _digest(nthreads: int) -> str:
    code = (
        "import hashlib, numpy as np, sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from test_raster import look_at_camera, random_scene\n"
        "from opacityhull.optimize.raster import rasterize, rasterize_backward\n"
        "cam = look_at_camera((0.3, 0.2, 2.2), width=61, height=47, f=60.0)\n"
        "p = random_scene(4, 900, cam, ('coincident', 'edge_on'))\n"
        "out = rasterize(p, cam)\n"
        "rng = np.random.default_rng(0)\n"
        "g = rasterize_backward(out, p, cam, dL_dimage=rng.normal(size=(47, 61, 3)), dL_dalpha=rng.normal(size=(47, 61)))\n"
        "h = hashlib.sha256()\n"
        "for a in (out.image, out.alpha, out.depth, g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, g.means2d_abs):\n"
        "    h.update(np.ascontiguousarray(a).tobytes())\n"
        "print(h.hexdigest())\n"
    )
    env = {**os.environ, "NUMBA_NUM_THREADS": str(nthreads)}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return res.stdout.strip().splitlines()[-1]


def test_same_bytes_every_run_and_thread_count():
    cam = look_at_camera((0.3, 0.2, 2.2), width=61, height=47, f=60.0)
    p = random_scene(4, 900, cam, ("coincident", "edge_on"))
    digests = []
    for _ in range(2):
        out = rasterize(p, cam)
        rng = np.random.default_rng(0)
        g = rasterize_backward(out, p, cam, dL_dimage=rng.normal(size=(47, 61, 3)), dL_dalpha=rng.normal(size=(47, 61)))
        h = hashlib.sha256()
        for a in (
            out.image,
            out.alpha,
            out.depth,
            g.means,
            g.quats,
            g.log_scales,
            g.opacity_logits,
            g.colors,
            g.means2d_abs,
        ):
            h.update(np.ascontiguousarray(a).tobytes())
        digests.append(h.hexdigest())
    assert digests[0] == digests[1]
    assert _digest(1) == _digest(2) == digests[0]


def test_bad_input_is_named():
    cam = look_at_camera((0.0, 0.0, 3.0))
    p = random_scene(0, 3, cam)
    with pytest.raises(ShapeError, match="quats"):
        SplatParams(**{**{k: getattr(p, k) for k in FIELDS}, "quats": np.zeros((3, 3), np.float32)})
    with pytest.raises(ShapeError, match="K"):
        RasterCamera(K=np.eye(2), cam_from_world=np.zeros((3, 4)), width=4, height=4)
    with pytest.raises(InputError, match="lowpass_px2"):
        RasterConfig(lowpass_px2=0.0)
    out = rasterize(p, cam)
    with pytest.raises(ShapeError, match="dL_dimage"):
        rasterize_backward(out, p, cam, dL_dimage=np.zeros((H, W)), dL_dalpha=None)
    with pytest.raises(InputError, match="forward"):
        rasterize_backward(
            out, p, cam, dL_dimage=np.zeros((H, W, 3)), dL_dalpha=None, config=replace(RasterConfig(), tile_px=8)
        )


@settings(max_examples=10, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31 - 1))
def test_surfel_order_does_not_change_results(cam, seed):
    """Rendering the surfels in another memory order (here raster.spatial_order's Morton
    order) gives the same image bytes and the same gradients, permuted."""
    from opacityhull.optimize.raster import spatial_order

    p = random_scene(seed, 60, cam)
    perm = spatial_order(p.means)
    assert sorted(perm.tolist()) == list(range(60))
    q = SplatParams(**{k: getattr(p, k)[perm] for k in FIELDS})
    wi, wa = _loss_weights(seed)
    a, b = rasterize(p, cam), rasterize(q, cam)
    assert a.image.tobytes() == b.image.tobytes() and a.alpha.tobytes() == b.alpha.tobytes()
    ga = rasterize_backward(a, p, cam, dL_dimage=wi, dL_dalpha=wa)
    gb = rasterize_backward(b, q, cam, dL_dimage=wi, dL_dalpha=wa)
    for k in (*FIELDS, "means2d_abs"):
        np.testing.assert_array_equal(getattr(ga, k)[perm], getattr(gb, k), err_msg=k)


def test_no_surfels_and_all_culled_give_the_background():
    cam = look_at_camera((0.0, 0.0, 3.0))
    empty = SplatParams(
        means=np.zeros((0, 3), np.float32),
        quats=np.zeros((0, 4), np.float32),
        log_scales=np.zeros((0, 2), np.float32),
        opacity_logits=np.zeros(0, np.float32),
        colors=np.zeros((0, 3), np.float32),
    )
    culled = random_scene(2, 0, cam, ("behind", "outside"))
    for p in (empty, culled):
        out = rasterize(p, cam, config=RasterConfig(background=(0.25, 0.5, 1.0)))
        assert out.n_fragments == 0 and not out.visible.any()
        np.testing.assert_array_equal(out.image, np.broadcast_to(np.float32([0.25, 0.5, 1.0]), (H, W, 3)))
        assert not out.alpha.any() and not out.depth.any()
        g = rasterize_backward(
            out,
            p,
            cam,
            dL_dimage=np.ones((H, W, 3)),
            dL_dalpha=np.ones((H, W)),
            config=RasterConfig(background=(0.25, 0.5, 1.0)),
        )
        for k in (*FIELDS, "means2d_abs"):
            assert getattr(g, k).shape == getattr(p, k if k != "means2d_abs" else "opacity_logits").shape
            assert not getattr(g, k).any()


def test_from_camera_projects_like_camera_project():
    """RasterCamera.from_camera keeps the project's conventions: the rasterizer's screen
    centres are Camera.project's pixels (OpenCV, pixel centres at integer coordinates)."""
    from opacityhull.camera import Camera
    from opacityhull.optimize.raster_reference import screen_covariance_reference

    rc = look_at_camera((0.7, -0.4, 2.6), f=37.0, pp=(1.3, -0.8))
    M = np.eye(4)
    M[:3] = rc.cam_from_world
    cam = Camera(K=rc.K, width=W, height=H, world_from_cam=np.linalg.inv(M), name="c0")
    p = random_scene(9, 20, rc)
    _, mu, _ = screen_covariance_reference(p, RasterCamera.from_camera(cam))
    uv, _ = cam.project(np.asarray(p.means, np.float64))
    np.testing.assert_allclose(mu, uv, atol=1e-9)
    distorted = Camera(
        K=rc.K, width=W, height=H, world_from_cam=np.linalg.inv(M), dist=np.array([0.1, 0, 0, 0, 0]), name="c1"
    )
    with pytest.raises(InputError, match="c1"):
        RasterCamera.from_camera(distorted)
    assert RasterCamera.from_camera(distorted, ignore_distortion=True).width == W


@pytest.mark.parametrize("field", FIELDS)
def test_nan_parameters_are_refused_naming_the_field(field):
    cam = look_at_camera((0.0, 0.0, 3.0))
    p = random_scene(1, 3, cam)
    arr = getattr(p, field).copy()
    arr.reshape(-1)[1] = np.nan
    with pytest.raises(InputError, match=f"{field} has 1 NaN"):
        rasterize(SplatParams(**{**{k: getattr(p, k) for k in FIELDS}, field: arr}), cam)
