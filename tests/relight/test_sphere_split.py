"""The sphere split (Matusik et al. 2002): every direction of an environment map is
counted once, by the display field or by the light array.

Oracles: the exact texel solid angles (sum 4π), and the analytic solid angle of each
display rectangle seen from the centre (Van Oosterom & Strackee's triangle formula),
independent of the ray-rectangle test the split uses.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import InputError
from opacityhull.envmap import EnvironmentMap
from opacityhull.relight.split import sphere_split, split_envmap
from opacityhull.sim.groundtruth import default_geometry


def _triangle_solid_angle(a, b, c) -> float:
    la, lb, lc = (float(np.linalg.norm(v)) for v in (a, b, c))
    num = abs(float(np.dot(a, np.cross(b, c))))
    den = la * lb * lc + float(np.dot(a, b)) * lc + float(np.dot(a, c)) * lb + float(np.dot(b, c)) * la
    return 2.0 * math.atan2(num, den)


def _rect_solid_angle(corners, centre) -> float:
    p = np.asarray(corners, np.float64) - np.asarray(centre, np.float64)
    return _triangle_solid_angle(p[0], p[1], p[2]) + _triangle_solid_angle(p[0], p[2], p[3])


def _object_corners(disp, table_deg):
    from opacityhull.camera import object_from_rig

    P = disp.corners_rig(table_deg)
    # corners_rig turns the table-fixed panels with the table; the object frame turns
    # the rig by -table: a panel on the table is fixed there, the others turn
    T = object_from_rig(table_deg)
    return P @ T[:3, :3].T + T[:3, 3]


GEOM = default_geometry()


@settings(max_examples=8, deadline=None)
@given(table=st.floats(0.0, 360.0), h=st.integers(8, 48), seed=st.integers(0, 2**16))
def test_every_direction_counted_once(table, h, seed):
    w = 2 * h
    s = sphere_split(h, w, GEOM.displays, table, supersample=3)
    assert np.all(s.display_weight >= 0) and np.all(s.display_weight <= 1)
    np.testing.assert_allclose(s.display_weight + s.array_weight, 1.0, atol=1e-15)
    assert s.display_solid_angle_sr() + s.array_solid_angle_sr() == pytest.approx(4 * math.pi, rel=1e-12)
    # a synthetic map: the two parts sum back to it, texel by texel, and their integrals
    env = EnvironmentMap(np.random.default_rng(seed).gamma(0.5, size=(h, w, 3)).astype(np.float32))
    arr, dsp = split_envmap(env, s)
    np.testing.assert_allclose(arr.radiance + dsp.radiance, env.radiance, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(arr.integral() + dsp.integral(), env.integral(), rtol=1e-5)


@pytest.mark.parametrize("table", [0.0, 37.0, 180.0])
def test_display_solid_angle_matches_the_rectangles(table):
    """The display weights integrate to the union of the panels' analytic solid angles
    (the built-in rig's back and bottom panels do not overlap as seen from the centre)."""
    centre = np.array([0.0, 0.05, 0.0])
    s = sphere_split(64, 128, GEOM.displays, table, centre_m=centre, supersample=6)
    expected = sum(_rect_solid_angle(_object_corners(d, table), centre) for d in GEOM.displays)
    assert s.display_solid_angle_sr() == pytest.approx(expected, rel=0.01)
    assert 0.0 < expected < 4 * math.pi


def test_no_displays_gives_everything_to_the_array():
    s = sphere_split(8, 16, (), 0.0)
    assert np.all(s.array_weight == 1.0) and s.display_solid_angle_sr() == 0.0


def test_bad_sizes_are_named():
    with pytest.raises(InputError, match="supersample"):
        sphere_split(8, 16, GEOM.displays, 0.0, supersample=0)
    with pytest.raises(InputError, match="map size"):
        sphere_split(0, 16, GEOM.displays, 0.0)
