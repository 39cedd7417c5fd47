"""The relighting chunks of a viewer bundle (``manifest["relight"]``, layout in
``docs/viewer-format.md``).

The page relights as :class:`opacityhull.relight.relit.Relighter` does — view i under
lighting L is ``Σ_l w_l(L, table_deg_i) ⊙ O_il`` over its one-light images O_il — from
a compressed form of the one-light stacks:

* per view a rank-r PCA of its (near-light corrected, matte-masked) stack,
  :func:`opacityhull.relight.relit.compress_reflectance`: r eigen-images ``B_ij`` and
  coefficients ``C_i`` (K × r), so ``relit_i = Σ_j (Σ_l w_l C_i[l, j]) B_ij``. The
  eigen-images are cropped to the bounding box of the view's matte (outside it the
  relit colour is 0 anyway) and stored as signed bytes with one scale per (view,
  component); r is one rank for all views, the smallest whose *relit* error (over the
  bundled maps at four yaws) is at most ``rel_error_target``;
* per bundled environment map the calibrated per-light RGB weights at ``yaw_steps``
  rotations and each distinct table angle, computed by :meth:`Relighter.weights` itself
  with the map turned by ``EnvironmentMap.rotated`` — the numbers the CPU relighter
  uses for ``load_envmap(spec, yaw_deg=yaw)``, so page and CPU agree by construction.
  Between steps the page interpolates linearly (the weights are linear in the map).

:func:`read_relight` reads the chunks back (the reference for the page's decoder) and
:func:`relit_views_from_bundle` relights views from them in NumPy.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import FormatError, InputError

log = logging.getLogger(__name__)

__all__ = [
    "RANK_MAX",
    "weight_table",
    "choose_rank",
    "quantize_basis",
    "write_relight",
    "read_relight",
    "relit_views_from_bundle",
]

RANK_MAX = 16
"""Largest PCA rank the page supports (a uniform array of the relight pass)."""


def weight_table(relighter, env, table_degs: Sequence[float], *, yaw_steps: int = 72) -> np.ndarray:
    """(S, T, K, 3) float64 calibrated weights ``relighter.weights(table_degs[t],
    envmap=env.rotated(360 s / S))`` for S = ``yaw_steps`` rotations of ``env`` (an
    :class:`~opacityhull.envmap.EnvironmentMap` at yaw 0) about +Y."""
    S = int(yaw_steps)
    if S < 1:
        raise InputError(f"yaw_steps {yaw_steps!r}: expected at least 1 rotation step")
    out = np.empty((S, len(table_degs), len(relighter.lights), 3))
    for s in range(S):
        e = env.rotated(360.0 * s / S)
        for t, a in enumerate(table_degs):
            out[s, t] = relighter.weights(float(a), envmap=e)
    return out


def relit_error_by_rank(comp, stack: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Squared relit errors of one view at ranks 1..R and the squared norm of the exact
    relit images: ``(Σ‖E − E_r‖² for r = 1..R, Σ‖E‖²)`` over the (M, K, 3) lightings
    ``weights``, E = Σ_k w_k ⊙ stack[k] and E_r its relighting from the first r
    components of ``comp`` (a rank-R :class:`~opacityhull.relight.relit.CompressedReflectance`
    of ``stack``)."""
    w = np.asarray(weights, np.float64)
    exact = np.einsum("khwc,mkc->mhwc", np.asarray(stack, np.float64), w)
    a = np.einsum("kr,mkc->mrc", comp.coeffs, w)  # (M, R, 3)
    acc = np.zeros_like(exact)
    B = comp.basis.astype(np.float64)
    err2 = np.zeros(comp.rank)
    for j in range(comp.rank):
        acc += B[j][None] * a[:, j][:, None, None, :]
        err2[j] = float(np.sum((exact - acc) ** 2))
    return err2, float(np.sum(exact**2))


def choose_rank(err2: np.ndarray, tot2: float, *, target: float) -> tuple[int, list[float]]:
    """Smallest rank whose relative relit error ``sqrt(err2[r-1] / tot2)`` (summed over
    views and lightings) is at most ``target`` (else the largest); and the errors."""
    errs = [math.sqrt(float(e) / tot2) if tot2 > 0 else 0.0 for e in err2]
    ok = [j for j, e in enumerate(errs) if e <= target]
    return (ok[0] + 1 if ok else len(errs)), errs


def quantize_basis(basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, h, w, 3) float eigen-images → (int8 codes, (r,) scales): value ≈ scale · q / 127
    (symmetric, one scale per component: its largest magnitude)."""
    b = np.asarray(basis, np.float64)
    scale = np.abs(b).reshape(len(b), -1).max(axis=1) if b.size else np.zeros(len(b))
    safe = np.where(scale > 0, scale, 1.0)
    q = np.clip(np.round(b / safe[:, None, None, None] * 127.0), -127, 127).astype(np.int8)
    return q, scale


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return 0, 0, 0, 0
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def _crop(matte: np.ndarray, camera, positions: np.ndarray, *, margin_px: int = 2) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the bounding box of the matte's non-zero pixels (the relit colour
    is 0 elsewhere) intersected with that of the surfels' projections ± ``margin_px`` —
    the page samples a view only at projected node centres (inner nodes are means of
    their leaves, inside the same box), bilinearly; stray matte specks far from the
    object (matting noise) would otherwise stretch the box to the whole frame."""
    x0, y0, x1, y1 = _bbox(matte > 0)
    uv, z = camera.project(positions)
    ok = np.all(np.isfinite(uv), axis=1) & (np.asarray(z) > 0)
    if not ok.any():
        return 0, 0, 0, 0
    u, v = uv[ok, 0], uv[ok, 1]
    x0 = max(x0, int(math.floor(u.min())) - margin_px)
    y0 = max(y0, int(math.floor(v.min())) - margin_px)
    x1 = min(x1, int(math.ceil(u.max())) + margin_px + 1)
    y1 = min(y1, int(math.ceil(v.max())) + margin_px + 1)
    if x1 <= x0 or y1 <= y0:
        return 0, 0, 0, 0
    return x0, y0, x1, y1


def _near_scaled(relighter, i: int, stack: np.ndarray) -> np.ndarray:
    """The stack with the near-light factor of each sample applied (what
    ``Relighter.relight_view`` compresses when ``pca_rank`` is set), through the public
    kernel: one-hot weights select one light each."""
    from ..relight.relit import relight_stack, view_surface_points

    if not relighter.near_light:
        return stack
    K = stack.shape[0]
    pts = view_surface_points(relighter.model, i)
    lp = relighter.light_positions_object(relighter.model.views[i].table_deg)
    eye = np.repeat(np.eye(K)[:, :, None], 3, axis=2)
    return relight_stack(stack, eye, points=pts, light_positions=lp)


def write_relight(
    tmp: Path,
    model,
    *,
    probes: Sequence[str],
    extra_envmap: tuple[str, float, str] | None = None,
    yaw_steps: int = 72,
    rel_error_target: float = 0.01,
    rank: int | None = None,
    progress: Callable[[], None] | None = None,
) -> dict:
    """Write ``basis.bin``, ``coeffs.bin``, ``weights_NN.bin`` and ``relight_env_NN.bin``
    into the bundle folder ``tmp``; returns the ``manifest["relight"]`` block.

    ``probes`` are builtin probe names; ``extra_envmap`` = (spec, default yaw, background
    file already in the bundle) adds the ``--envmap`` map. ``rank`` fixes the PCA rank
    (default: chosen by ``rel_error_target``). ``progress()`` is called once per view.
    """
    from ..relight.envmap import default_yaw_deg, load_envmap
    from ..relight.relit import Relighter
    from ..pictures import auto_exposure

    R = Relighter(model)
    V, K = len(model.views), len(R.lights)
    if not 0 < rel_error_target < 1 or not math.isfinite(rel_error_target):
        raise InputError(f"--relight-error {rel_error_target!r}: expected a relative error in (0, 1)")
    if rank is not None and not 1 <= int(rank) <= min(K, RANK_MAX):
        raise InputError(f"--relight-rank {rank}: expected 1..{min(K, RANK_MAX)} (lights {K}, page limit {RANK_MAX})")
    envs: list[tuple[str, str, float, str | None]] = [
        (f"builtin:{p}", p, default_yaw_deg(f"builtin:{p}"), None) for p in probes
    ]
    if extra_envmap is not None:
        spec, yaw, bgfile = extra_envmap
        name = spec[8:] if spec.startswith("builtin:") else Path(spec).stem
        same = [n for n, e in enumerate(envs) if e[0] == spec]
        if same:  # a bundled probe: its entry keeps this yaw and shares the --envmap image
            envs[same[0]] = (spec, name, yaw, bgfile)
        else:
            envs.append((spec, name, yaw, bgfile))
    if not envs:
        raise InputError("relit bundle: no environment map to relight with (give --probes or --envmap)")
    tables = sorted({round(float(v.table_deg) % 360.0, 9) for v in model.views})
    t_index = [tables.index(round(float(v.table_deg) % 360.0, 9)) for v in model.views]
    S = int(yaw_steps)
    env_meta, tables_w = [], []
    for n, (spec, name, yaw0, bgfile) in enumerate(envs):
        env = load_envmap(spec)
        W = weight_table(R, env, tables, yaw_steps=S)
        tables_w.append(W)
        wf = f"weights_{n:02d}.bin"
        W32 = W.astype("<f4")
        (tmp / wf).write_bytes(W32.tobytes())
        if bgfile is None:
            img = np.ascontiguousarray(env.radiance, dtype="<f4")
            bgfile = f"relight_env_{n:02d}.bin"
            (tmp / bgfile).write_bytes(img.tobytes())
        env_meta.append(
            {
                "name": name,
                "source": spec,
                "default_yaw_deg": float(yaw0) % 360.0,
                "weights": {"file": wf, "bytes": W32.nbytes},
                "image": {
                    "file": bgfile,
                    "width": env.width,
                    "height": env.height,
                    "bytes": env.width * env.height * 12,
                },
            }
        )
    from ..relight.relit import compress_reflectance

    # per view: the stack cropped to the matte and masked, near-light corrected, its
    # rank-R PCA (eigen-images kept as bytes: memory stays ~R bytes per cropped pixel),
    # and its relit errors under every bundled map at four yaws (to choose the rank)
    r_max = min(K, RANK_MAX)
    quarter = [0, S // 4, S // 2, (3 * S) // 4] if S >= 4 else list(range(S))
    mid = V // 2
    P_all = np.asarray(model.surfels.positions, np.float64)
    P_all = P_all[np.all(np.isfinite(P_all), axis=1)]
    err2, tot2 = np.zeros(r_max), 0.0
    per_view = []
    for i in range(V):
        a = R.matte(i)
        x0, y0, x1, y1 = _crop(a, model.views[i].camera, P_all)
        s = _near_scaled(R, i, R.load_stack(i))
        s = s[:, y0:y1, x0:x1] * (a[y0:y1, x0:x1] > 0)[None, :, :, None]
        if s.size == 0:
            s = np.zeros((K, 1, 1, 3), np.float32)
        s = np.ascontiguousarray(s, np.float32)
        c = compress_reflectance(s, r_max)
        e2, t2 = relit_error_by_rank(c, s, np.concatenate([W[quarter, t_index[i]] for W in tables_w]))
        err2 += e2
        tot2 += t2
        q, scale = quantize_basis(c.basis)
        per_view.append((q, scale, c.coeffs, c.singular_values, (x0, y0)))
        if i == mid:  # one exposure per map, as relight_model picks it (middle view, default yaw)
            am = a[y0:y1, x0:x1] if s.shape[1:3] == (y1 - y0, x1 - x0) else np.zeros(s.shape[1:3], np.float32)
            for n, em in enumerate(env_meta):
                s0 = int(round(em["default_yaw_deg"] / (360.0 / S))) % S
                rgb = np.einsum("khwc,kc->hwc", s.astype(np.float64), tables_w[n][s0, t_index[i]])
                em["exposure"] = auto_exposure(rgb, am)
        if progress:
            progress()
    r_sel, errs = choose_rank(err2, tot2, target=rel_error_target)
    r = int(rank) if rank is not None else r_sel
    Wc = max(pv[0].shape[2] for pv in per_view)
    Hc = max(pv[0].shape[1] for pv in per_view)
    cols = math.ceil(math.sqrt(r))
    rows = math.ceil(r / cols)
    coeffs = np.zeros((V, K, r), "<f4")
    views_meta = []
    stack_err = []
    with open(tmp / "basis.bin", "wb") as f:
        for i, (q, scale, C, sv, crop) in enumerate(per_view):
            layer = np.zeros((rows * Hc, cols * Wc, 3), np.int8)
            h, w = q.shape[1:3]
            for j in range(r):
                ty, tx = divmod(j, cols)
                layer[ty * Hc : ty * Hc + h, tx * Wc : tx * Wc + w] = q[j]
            f.write(layer.tobytes())
            coeffs[i] = C[:, :r]
            tot = float(np.sum(sv**2))
            e = math.sqrt(max(0.0, float(np.sum(sv[r:] ** 2))) / tot) if tot > 0 else 0.0
            stack_err.append(e)
            views_meta.append(
                {
                    "table_index": t_index[i],
                    "crop": [int(crop[0]), int(crop[1])],
                    "scale": [float(x) for x in scale[:r]],
                    "stack_rel_error": e,
                }
            )
    (tmp / "coeffs.bin").write_bytes(coeffs.tobytes())
    basis_bytes = V * rows * Hc * cols * Wc * 3
    return {
        "n_lights": K,
        "light_keys": list(R.lights.keys),
        "near_light": bool(R.near_light),
        "rank": r,
        "rank_max": r_max,
        "rel_error_target": float(rel_error_target),
        "relit_rel_error": errs[r - 1],
        "relit_rel_error_by_rank": errs,
        "stack_rel_error_mean": float(np.mean(stack_err)),
        "stack_rel_error_max": float(np.max(stack_err)),
        "table_deg": tables,
        "yaw_steps": S,
        "basis": {
            "file": "basis.bin",
            "bytes": basis_bytes,
            "tile_width": Wc,
            "tile_height": Hc,
            "cols": cols,
            "rows": rows,
            "layer_width": cols * Wc,
            "layer_height": rows * Hc,
            "encoding": "int8 RGB (RGB8_SNORM): eigen-image j of view v = scale[v][j] * q / 127, tile j at "
            "(j % cols, j // cols) of layer v, pixel (x, y) of the tile is view pixel (crop_x + x, crop_y + y)",
        },
        "coeffs": {"file": "coeffs.bin", "bytes": coeffs.nbytes, "encoding": "float32 (views, lights, rank)"},
        "views": views_meta,
        "envmaps": env_meta,
    }


def read_relight(bundle_dir) -> tuple[dict, np.ndarray, np.ndarray, list[np.ndarray]]:
    """(relight block, basis (V, r, Hc, Wc, 3) float32 with the scales applied, coeffs
    (V, K, r), per map the (S, T, K, 3) weights) of a bundle; FormatError naming the file
    when a chunk is missing or of the wrong size."""
    root = Path(bundle_dir)
    try:
        man = json.loads((root / "manifest.json").read_text())
    except (OSError, ValueError) as e:
        raise FormatError(f"{root}/manifest.json: not a viewer bundle ({e})") from e
    rl = man.get("relight")
    if not rl:
        raise FormatError(f"{root}/manifest.json: the bundle has no relighting data (model without reflectance)")

    def raw(meta, what):
        p = root / meta["file"]
        try:
            b = p.read_bytes()
        except OSError as e:
            raise FormatError(f"{p}: {what} missing ({e.strerror})") from None
        if len(b) != meta["bytes"]:
            raise FormatError(f"{p}: {what} has {len(b)} bytes, expected {meta['bytes']}")
        return b

    V, K, r = len(rl["views"]), rl["n_lights"], rl["rank"]
    B = rl["basis"]
    q = np.frombuffer(raw(B, "the PCA basis"), np.int8).reshape(V, B["layer_height"], B["layer_width"], 3)
    basis = np.zeros((V, r, B["tile_height"], B["tile_width"], 3), np.float32)
    for v, vm in enumerate(rl["views"]):
        for j in range(r):
            ty, tx = divmod(j, B["cols"])
            t = q[
                v,
                ty * B["tile_height"] : (ty + 1) * B["tile_height"],
                tx * B["tile_width"] : (tx + 1) * B["tile_width"],
            ]
            basis[v, j] = t.astype(np.float32) * np.float32(vm["scale"][j] / 127.0)
    coeffs = np.frombuffer(raw(rl["coeffs"], "the PCA coefficients"), "<f4").reshape(V, K, r)
    S, T = rl["yaw_steps"], len(rl["table_deg"])
    weights = [
        np.frombuffer(raw(e["weights"], f"the light weights of {e['name']}"), "<f4").reshape(S, T, K, 3)
        for e in rl["envmaps"]
    ]
    return rl, basis, coeffs, weights


def relit_views_from_bundle(bundle_dir, env_index: int, yaw_deg: float, shapes) -> list[np.ndarray]:
    """Per view the (H, W, 3) relit premultiplied colour the page computes (float32),
    ``shapes`` the views' (H, W): weights interpolated between yaw steps, PCA basis
    decoded from its bytes."""
    rl, basis, coeffs, weights = read_relight(bundle_dir)
    W = weights[env_index]
    S = rl["yaw_steps"]
    x = (float(yaw_deg) % 360.0) / (360.0 / S)
    s0 = int(math.floor(x))
    f = x - s0
    w = (1 - f) * W[s0 % S].astype(np.float64) + f * W[(s0 + 1) % S].astype(np.float64)
    out = []
    for v, vm in enumerate(rl["views"]):
        a = np.einsum("kc,kr->rc", w[vm["table_index"]], coeffs[v].astype(np.float64))
        crop = np.maximum(np.einsum("rhwc,rc->hwc", basis[v].astype(np.float64), a), 0.0)
        H, Wd = shapes[v]
        img = np.zeros((H, Wd, 3), np.float32)
        x0, y0 = vm["crop"]
        h = min(crop.shape[0], H - y0)
        wd = min(crop.shape[1], Wd - x0)
        if h > 0 and wd > 0:
            img[y0 : y0 + h, x0 : x0 + wd] = crop[:h, :wd]
        out.append(img)
    return out
