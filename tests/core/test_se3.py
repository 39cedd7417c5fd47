"""The SE(3)/SO(3) helpers against independent references (SciPy's Rotation, a general
matrix inverse), with the hard cases: angles near 0 and 180 deg, reflections, identical
and opposite-weighted poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from opacityhull import se3

rotvecs = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=30, deadline=None)
@given(rotvecs, st.lists(st.floats(-10.0, 10.0, allow_nan=False), min_size=3, max_size=3))
def test_rodrigues_and_inverse_match_scipy(rv, t):
    R = se3.rodrigues(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    T = se3.rigid(R, t)
    np.testing.assert_allclose(se3.invert_rigid(T), np.linalg.inv(T), atol=1e-9)
    if np.linalg.norm(rv) > 1e-4:  # OpenCV returns 0 below ~1e-5 rad (next test)
        np.testing.assert_allclose(se3.rodrigues(se3.rvec_from_matrix(R)), R, atol=1e-9)
    assert se3.rotation_angle_deg(R) == pytest.approx(math.degrees(Rotation.from_rotvec(rv).magnitude()), abs=1e-6)


def test_rvec_from_matrix_round_trip_and_its_small_angle_floor():
    rv = np.array([0.0, 0.0, 1e-4])
    np.testing.assert_allclose(se3.rvec_from_matrix(se3.rodrigues(rv)), rv, rtol=1e-6)
    np.testing.assert_allclose(se3.rvec_from_matrix(se3.rodrigues([0.5, -2.0, 1.0])), [0.5, -2.0, 1.0], atol=1e-12)
    # Documented OpenCV behaviour: a rotation below ~1e-5 rad becomes the zero vector.
    np.testing.assert_array_equal(se3.rvec_from_matrix(se3.rodrigues([0.0, 0.0, 1e-6])), np.zeros(3))


@pytest.mark.parametrize("angle_deg", [0.0, 1e-7, 0.01, 90.0, 179.99, 180.0])
def test_rotation_angle_is_accurate_near_0_and_180(angle_deg):
    R = Rotation.from_rotvec(np.radians(angle_deg) * np.array([0.6, 0.0, 0.8])).as_matrix()
    assert se3.rotation_angle_deg(R) == pytest.approx(angle_deg, abs=1e-9 + 1e-9 * angle_deg)


def test_axis_rotation_is_right_handed():
    # +90 deg about +Y turns +Z towards +X (the rig's table convention).
    np.testing.assert_allclose(
        se3.axis_rotation([0.0, 1.0, 0.0], math.pi / 2) @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-15
    )


def test_project_to_so3_fixes_reflections_and_noise():
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    P = se3.project_to_so3(R + rng.normal(0.0, 1e-3, (3, 3)))
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(P) == pytest.approx(1.0, abs=1e-12)
    assert se3.rotation_angle_deg(P.T @ R) < 0.2
    M = np.diag([1.0, 1.0, -1.0])  # a reflection: the nearest rotation has det +1
    assert np.linalg.det(se3.project_to_so3(M)) == pytest.approx(1.0)


def test_mean_pose_of_identical_and_symmetric_poses():
    T = se3.rigid(se3.rodrigues([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(se3.mean_pose([T, T, T]), T, atol=1e-12)
    # ±10 deg about +Y around T, translations ±1 in x, weights equal: the mean is T.
    Ra, Rb = se3.axis_rotation([0, 1, 0], math.radians(10)), se3.axis_rotation([0, 1, 0], math.radians(-10))
    A = se3.rigid(T[:3, :3] @ Ra, T[:3, 3] + [1.0, 0, 0])
    B = se3.rigid(T[:3, :3] @ Rb, T[:3, 3] - [1.0, 0, 0])
    np.testing.assert_allclose(se3.mean_pose([A, B]), T, atol=1e-12)
    # weights pull the translation
    np.testing.assert_allclose(se3.mean_pose([A, B], [3.0, 1.0])[:3, 3], T[:3, 3] + [0.5, 0, 0], atol=1e-12)


def test_wrap_deg():
    np.testing.assert_array_equal(
        se3.wrap_deg([-180.0, 180.0, 190.0, -190.0, 359.0, 0.0]), [-180.0, -180.0, -170.0, 170.0, -1.0, 0.0]
    )
