"""Floating textures: optical-flow alignment of the source views before ULR blending.

Where the geometry is only the visual hull, each source view projects a surface point to
the wrong place in the novel view, by a different amount per view; blending them
ghosts (double edges, smeared texture). Eisemann et al. 2008 ("Floating Textures")
remove most of it in image space: with the per-view projections ``I_j`` of the views
into the novel view (each view's texture fetched at the back-projected surface point),
estimate the optical flow between every pair, move every ``I_j`` by the blending-weighted
mean of its flows to the others, and blend the moved images with the unchanged weights.
Each view then lands where the weighted consensus of the views puts the texture — the
midpoint between two neighbours for a viewpoint halfway between them, which is where a
surface point at the correct depth would appear.

Here, on top of the per-pixel ("deferred") shading (:mod:`.deferred`):

1. ``ulr_select`` gives per shaded pixel the k chosen views, their ULR weights and
   texture positions — the same choice and weights as :func:`~.deferred.deferred_shade`.
2. The views carrying at least ``min_share`` of the frame's total weight (at most
   ``max_views``) get a full-frame projection ``I_j`` (bilinear premultiplied RGBA at
   every back-projected point); where ``j`` is not among a pixel's chosen views the
   unaligned blend stands in, so the flow there is ~0 and no edge of ``I_j``'s support is
   mistaken for motion.
3. Flow ``F_ij`` with ``I_i(x) ≈ I_j(x + F_ij(x))``: OpenCV's DIS optical flow (Kroeger
   et al. 2016) on 8-bit sRGB luminance, both directions of every pair.
4. Displacement of view j: ``D_j(x) = Σ_i ŵ_i(x) F_ij(x)`` over the pixel's chosen views
   (ŵ the ULR weights, F_jj = 0), scaled by ``strength`` and clamped to ``max_flow_px``.
5. The view's *texture position* map (its pixel coordinates for every back-projected
   point) is resampled at ``x + D_j(x)`` and the source view sampled there once (no
   double resampling of colour), then blended with the weights of step 1.

With zero displacement the result equals :func:`~.deferred.deferred_shade` (tested);
views outside the chosen set keep their unaligned contribution. Eisemann et al. also
weight by a soft visibility map; the winner's visibility bits play that part here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..errors import ConfigError
from . import kernels as K

__all__ = ["FlowAlignConfig", "float_blend", "dis_flow", "project_points"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class FlowAlignConfig:
    """Options of :func:`float_blend`.

    Parameters
    ----------
    max_views : int ≥ 2
        At most this many views (the heaviest by total weight in the frame) are aligned.
    min_share : float in [0, 1)
        A view is aligned only if it carries at least this fraction of the frame's weight.
    strength : float in [0, 1]
        Fraction of the consensus displacement applied (1: Eisemann et al.'s rule).
    max_flow_px : float > 0
        Displacements are clamped to this length (px of the novel view): a flow vector
        longer than the geometry's plausible error is a mismatch.
    preset : "ultrafast" | "fast" | "medium"
        OpenCV DIS preset (speed vs accuracy of the flow).
    """

    max_views: int = 4
    min_share: float = 0.05
    strength: float = 1.0
    max_flow_px: float = 12.0
    preset: str = "medium"

    def __post_init__(self):
        if not (isinstance(self.max_views, int) and self.max_views >= 2):
            raise ConfigError(f"align max_views must be an integer >= 2, got {self.max_views!r}")
        if not 0.0 <= float(self.min_share) < 1.0:
            raise ConfigError(f"align min_share must be in [0, 1), got {self.min_share!r}")
        if not 0.0 <= float(self.strength) <= 1.0:
            raise ConfigError(f"align strength must be in [0, 1], got {self.strength!r}")
        if not float(self.max_flow_px) > 0.0:
            raise ConfigError(f"align max_flow_px must be > 0, got {self.max_flow_px!r}")
        if self.preset not in ("ultrafast", "fast", "medium"):
            raise ConfigError(f"align preset must be ultrafast, fast or medium, got {self.preset!r}")


@njit(cache=True, nogil=True, error_model="numpy")
def project_points(cams, v, points, out):  # pragma: no cover - compiled
    """(P, 3) object-frame points → (P, 2) pixel positions in packed view ``v`` (nan behind it)."""
    for i in range(points.shape[0]):
        u, y, _ = K._project(cams, v, points[i, 0], points[i, 1], points[i, 2])
        out[i, 0] = u
        out[i, 1] = y


def _display_grey(premul: np.ndarray) -> np.ndarray:
    """8-bit sRGB-ish luminance of a premultiplied RGBA image (over black): what the flow sees."""
    lum = premul[..., 0] * 0.299 + premul[..., 1] * 0.587 + premul[..., 2] * 0.114
    return (np.clip(np.nan_to_num(lum), 0.0, 1.0) ** (1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)


def dis_flow(prev: np.ndarray, nxt: np.ndarray, *, preset: str = "medium") -> np.ndarray:
    """Dense optical flow (H, W, 2) float32 with ``prev(x) ≈ nxt(x + flow(x))`` (OpenCV DIS
    on two (H, W) uint8 images)."""
    import cv2

    code = {
        "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
        "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
        "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    }[preset]
    dis = cv2.DISOpticalFlow.create(code)
    return dis.calc(prev, nxt, None)  # pyright: ignore[reportCallIssue, reportArgumentType]  (flow=None: allocate)


def _fetch(views, v: int, uv: np.ndarray) -> np.ndarray:
    out = np.zeros((uv.shape[0], 4), np.float32)
    ok = np.isfinite(uv).all(axis=1)
    if ok.any():
        K.bilinear_fetch(
            views.texels,
            views.offsets[v],
            int(views.sizes[v, 0]),
            int(views.sizes[v, 1]),
            np.ascontiguousarray(uv[ok], np.float32),
            tmp := np.empty((int(ok.sum()), 4), np.float32),
        )
        out[ok] = tmp
    return out


def float_blend(
    pix: np.ndarray,
    points: np.ndarray,
    idx: np.ndarray,
    w: np.ndarray,
    uv: np.ndarray,
    views,
    shape: tuple[int, int],
    *,
    config: FlowAlignConfig = FlowAlignConfig(),
    flows: dict | None = None,
) -> tuple[np.ndarray, dict]:
    """ULR blend of the chosen views with floating-texture alignment.

    Parameters
    ----------
    pix : (P,) int64 flat pixel indices of the shaded pixels (row-major over ``shape``).
    points : (P, 3) back-projected surface points, object frame (m).
    idx, w, uv : (P, k) chosen view indices (−1 unused), ULR weights, and (P, k, 2) their
        texture positions (px), as ``kernels.ulr_select`` returns them.
    views : :class:`~opacityhull.render.views.PreparedViews` with images.
    shape : (H, W) of the frame.
    config : :class:`FlowAlignConfig`.
    flows : optional ``{(i, j): (H, W, 2) flow}`` to use instead of estimating them (the
        tests pass zeros to check the recomposition, or known shifts).

    Returns
    -------
    premul : (H, W, 4) float32 premultiplied RGBA (0 where not shaded), and stats
        (aligned views, mean displacement px, flow ms).
    """
    import time

    H, W = shape
    P, k = idx.shape
    out_flat = np.zeros((H * W, 4), np.float32)
    if P == 0:
        return out_flat.reshape(H, W, 4), {"aligned_views": [], "mean_shift_px": 0.0}
    # the unaligned blend (what deferred_shade returns)
    blend = np.zeros((P, 4), np.float32)
    per_view_w: dict[int, float] = {}
    for c in range(k):
        vc = idx[:, c]
        for v in np.unique(vc[vc >= 0]):
            sel = vc == v
            col = _fetch(views, int(v), uv[sel, c])
            blend[sel] += w[sel, c, None].astype(np.float32) * col
            per_view_w[int(v)] = per_view_w.get(int(v), 0.0) + float(w[sel, c].sum())
    total = sum(per_view_w.values())
    ranked = sorted(per_view_w, key=lambda v: -per_view_w[v])
    S = [v for v in ranked if per_view_w[v] >= config.min_share * total][: config.max_views]
    stats: dict = {"aligned_views": S, "mean_shift_px": 0.0}
    if len(S) < 2 or config.strength == 0.0:
        out_flat[pix] = blend
        return out_flat.reshape(H, W, 4), stats
    t0 = time.perf_counter()
    # per aligned view: its weight map and its texture-position map over the frame
    wmap = {v: np.zeros(H * W, np.float32) for v in S}
    for c in range(k):
        for v in S:
            sel = idx[:, c] == v
            wmap[v][pix[sel]] += w[sel, c]
    uvmap = {}
    proj = {}
    for v in S:
        q = np.empty((P, 2), np.float64)
        project_points(views.cams, int(v), np.ascontiguousarray(points, np.float64), q)
        m = np.full((H * W, 2), np.nan, np.float32)
        m[pix] = q
        uvmap[v] = m.reshape(H, W, 2)
        img = np.zeros((H * W, 4), np.float32)
        chosen = wmap[v][pix] > 0
        img[pix] = blend
        img[pix[chosen]] = _fetch(views, int(v), q[chosen])
        proj[v] = _display_grey(img.reshape(H, W, 4))
    if flows is None:
        flows = {}
        for i in S:
            for j in S:
                if i != j:
                    flows[(i, j)] = dis_flow(proj[i], proj[j], preset=config.preset)
    t_flow = time.perf_counter()
    import cv2

    wsum = np.zeros(H * W, np.float32)
    for v in S:
        wsum += wmap[v]
    shifts = []
    aligned = blend.copy()
    gy, gx = np.mgrid[0:H, 0:W].astype(np.float32)
    for j in S:
        D = np.zeros((H, W, 2), np.float32)
        for i in S:
            if i != j:
                D += wmap[i].reshape(H, W, 1) * flows[(i, j)]
        with np.errstate(invalid="ignore", divide="ignore"):
            D /= np.where(wsum > 0, wsum, 1.0).reshape(H, W, 1)
        D *= np.float32(config.strength)
        n = np.sqrt((D**2).sum(axis=2))
        lim = np.float32(config.max_flow_px)
        D *= np.where(n > lim, lim / np.maximum(n, 1e-12), 1.0)[..., None].astype(np.float32)
        # the view's texture position at x + D(x): remap its uv map (smooth within a
        # surface) rather than its colours, so colour is resampled once
        have = np.isfinite(uvmap[j]).all(axis=2)
        mx, my = gx + D[..., 0], gy + D[..., 1]
        moved = cv2.remap(np.where(have[..., None], uvmap[j], 0.0), mx, my, cv2.INTER_LINEAR)
        moved = moved.reshape(-1, 2)[pix]
        # where the displaced position touches a pixel without a texture position (off
        # the surface, or off the frame) the unmoved one stays
        inside = cv2.remap(have.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=0.0)
        bad = inside.reshape(-1)[pix] < 0.999
        base = uvmap[j].reshape(-1, 2)[pix]
        moved[bad] = base[bad]
        for c in range(k):
            sel = idx[:, c] == j
            if sel.any():
                old = _fetch(views, int(j), uv[sel, c])
                new = _fetch(views, int(j), moved[sel])
                aligned[sel] += w[sel, c, None].astype(np.float32) * (new - old)
        chosen = wmap[j][pix] > 0
        if chosen.any():
            shifts.append(float(n.reshape(-1)[pix[chosen]].mean()))
    out_flat[pix] = aligned
    stats["mean_shift_px"] = float(np.mean(shifts)) if shifts else 0.0
    stats["flow_ms"] = round(1000.0 * (t_flow - t0), 1)
    log.info("floating textures: %s", stats)
    return out_flat.reshape(H, W, 4), stats
