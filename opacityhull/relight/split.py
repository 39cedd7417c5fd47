"""The sphere split of Matusik et al. 2002: each direction of an environment map lights
the object through exactly one of the two captured reflectance fields.

* Directions the displays cover (seen from the object centre) come from the
  high-resolution display-domain field (the environment matte / natural-illumination
  field: :func:`~opacityhull.reconstruct.natural.relight_view_natural`), which samples
  them at the displays' pixel pitch.
* Every other direction comes from the low-resolution reflectance field of the light
  array (the one-light images, filtered to the array's angular sampling by
  :mod:`.basis`).

The split is a pair of per-texel weights over the equirectangular map,
``display_weight + array_weight = 1`` at every texel, where ``display_weight`` is the
*solid-angle fraction* of the texel the displays cover (the union of the displays, so a
direction two panels both cover counts once), estimated by ``supersample²`` sub-directions
stratified uniformly in solid angle (in cos θ and φ within the texel). The light-array
relighter is given ``array_weight × L`` and the display field the displays' own pixels,
so ``∫ L dω`` is split, never counted twice or lost. The fixed back display turns by
−table in the object frame, so the split depends on the view's table angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..envmap import EnvironmentMap, latlong_solid_angles

__all__ = ["SphereSplit", "sphere_split", "split_envmap"]


@dataclass(frozen=True, kw_only=True)
class SphereSplit:
    """Per-texel weights of an (H, W) lat-long map.

    Attributes
    ----------
    display_weight : (H, W) float64 in [0, 1], solid-angle fraction the displays cover.
    array_weight : (H, W) float64, ``1 - display_weight``: the light array's share.
    solid_angle_sr : (H, W) float64 texel solid angles (sum 4π).
    """

    display_weight: np.ndarray
    array_weight: np.ndarray
    solid_angle_sr: np.ndarray

    def display_solid_angle_sr(self) -> float:
        return float(np.sum(self.display_weight * self.solid_angle_sr))

    def array_solid_angle_sr(self) -> float:
        return float(np.sum(self.array_weight * self.solid_angle_sr))


def _subtexel_directions(height: int, width: int, ss: int) -> np.ndarray:
    """(H, W, ss*ss, 3) directions stratified uniformly in solid angle inside each texel
    (equal steps of cos θ within the row band, of φ within the column)."""
    edges = np.arange(height + 1) * (math.pi / height)
    c0, c1 = np.cos(edges[:-1]), np.cos(edges[1:])
    f = (np.arange(ss) + 0.5) / ss
    cos_t = c0[:, None] + (c1 - c0)[:, None] * f[None, :]  # (H, ss)
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, 1.0))
    phi = (np.arange(width)[:, None] + f[None, :]) * (2.0 * math.pi / width)  # (W, ss)
    # project convention (latlong_directions): (sin θ sin φ, cos θ, -sin θ cos φ)
    st = sin_t[:, None, :, None]
    ct = cos_t[:, None, :, None]
    sp = np.sin(phi)[None, :, None, :]
    cp = np.cos(phi)[None, :, None, :]
    x = st * sp
    y = np.broadcast_to(ct, x.shape)
    z = -st * cp
    d = np.stack([x, y, z], axis=-1)  # (H, W, ss_theta, ss_phi, 3)
    return d.reshape(height, width, ss * ss, 3)


def sphere_split(
    height: int,
    width: int,
    displays: Sequence,
    table_deg: float,
    *,
    centre_m=(0.0, 0.0, 0.0),
    supersample: int = 4,
) -> SphereSplit:
    """The solid-angle masks of the split for an (``height``, ``width``) lat-long map.

    Parameters
    ----------
    height, width : map size in texels.
    displays : the rig's :class:`~opacityhull.riggeometry.DisplaySpec` whose fields the
        model has (an empty sequence gives everything to the light array).
    table_deg : the view's table angle (the fixed displays turn by −table in the object frame).
    centre_m : (3,) object-frame point the directions are taken from (metres).
    supersample : sub-directions per texel side (≥ 1).

    Raises
    ------
    InputError
        A size or ``supersample`` below 1.
    """
    from ..reconstruct.natural import display_hit_mask

    if height < 1 or width < 1:
        raise InputError(f"sphere split: map size {width}x{height}, expected >= 1x1")
    if supersample < 1:
        raise InputError(f"sphere split: supersample {supersample}, expected >= 1")
    omega = np.broadcast_to(latlong_solid_angles(height, width)[:, None], (height, width)).copy()
    cover = np.zeros((height, width), np.float64)
    if displays:
        d = _subtexel_directions(height, width, supersample)
        hit = np.zeros(d.shape[:3], bool)
        for disp in displays:
            hit |= display_hit_mask(disp, table_deg, d, centre_m=centre_m)  # union: counted once
        cover = hit.mean(axis=2)
    return SphereSplit(display_weight=cover, array_weight=1.0 - cover, solid_angle_sr=omega)


def split_envmap(envmap: EnvironmentMap, split: SphereSplit) -> tuple[EnvironmentMap, EnvironmentMap]:
    """``(array part, display part)`` of ``envmap``: its radiance times each weight. The
    two sum to the map texel by texel."""
    if split.display_weight.shape != (envmap.height, envmap.width):
        raise InputError(
            f"sphere split of {split.display_weight.shape[::-1]} texels for a map of {envmap.width}x{envmap.height}"
        )
    L = envmap.radiance.astype(np.float64)
    arr = EnvironmentMap((L * split.array_weight[..., None]).astype(np.float32), f"{envmap.source} (light array part)")
    dsp = EnvironmentMap((L * split.display_weight[..., None]).astype(np.float32), f"{envmap.source} (display part)")
    return arr, dsp
