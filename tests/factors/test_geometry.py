from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from factors.geometry import (
    attitude_matrix,
    attitude_matrix_derivatives,
    detector_vector,
    drot_x,
    drot_y,
    drot_z,
    hermite_weights,
    line_fraction,
    orbital_frame,
    rot_x,
    rot_y,
    rot_z,
    skew,
)

angle = st.floats(-3.0, 3.0)


@given(angle)
def test_rotations_are_proper_orthonormal(a):
    for r in (rot_x(a), rot_y(a), rot_z(a)):
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(r) == pytest.approx(1.0)


@given(angle)
def test_rotation_derivatives_match_central_differences(a):
    h = 1e-6
    for r, dr in ((rot_x, drot_x), (rot_y, drot_y), (rot_z, drot_z)):
        num = (r(a + h) - r(a - h)) / (2 * h)
        np.testing.assert_allclose(dr(a), num, atol=1e-9)


def test_rot_z_is_active():
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


@given(angle, angle, angle)
def test_attitude_matrix_matches_eq5_with_corrected_element(roll, pitch, yaw):
    t = attitude_matrix(roll, pitch, yaw)
    sO, cO, sP, cP, sK, cK = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch), np.sin(yaw), np.cos(yaw)
    eq5 = np.array(
        [
            [cP * cK, sO * sP * cK - cO * sK, cO * sP * cK + sO * sK],
            [cP * sK, sO * sP * sK + cO * cK, cO * sP * sK - sO * cK],
            [-sP, sO * cP, cO * cP],
        ]
    )
    np.testing.assert_allclose(t, eq5, atol=1e-14)


def test_attitude_matrix_derivatives_numeric(rng):
    a = rng.normal(size=3)
    h = 1e-6
    _, *ders = attitude_matrix_derivatives(*a)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        num = (attitude_matrix(*(a + e)) - attitude_matrix(*(a - e))) / (2 * h)
        np.testing.assert_allclose(ders[i], num, atol=1e-9)


def test_orbital_frame_axes(rng):
    p = rng.normal(size=(20, 3)) * 7e6
    v = np.cross(p, rng.normal(size=(20, 3)))
    v = v / np.linalg.norm(v, axis=1, keepdims=True) * 7.5e3
    t = orbital_frame(p, v)
    np.testing.assert_allclose(t @ np.swapaxes(t, 1, 2), np.broadcast_to(np.eye(3), t.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(t), 1.0)
    # z toward nadir, x along velocity for a circular orbit
    np.testing.assert_allclose(t[:, :, 2], -p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-14)
    np.testing.assert_allclose(t[:, :, 0], v / np.linalg.norm(v, axis=1, keepdims=True), atol=1e-12)


def test_hermite_weights_reproduce_eq23_to_27(rng):
    ai, dai, aj, daj = rng.normal(size=4)
    dt = 60.0
    tau = np.linspace(0, 1, 11)
    c0, c1 = ai, dai * dt
    c2 = 3 * (aj - ai) - (daj + 2 * dai) * dt
    c3 = -2 * (aj - ai) + (daj + dai) * dt
    poly = c0 + c1 * tau + c2 * tau**2 + c3 * tau**3
    w = hermite_weights(tau, dt)
    np.testing.assert_allclose(w @ [ai, dai, aj, daj], poly, atol=1e-12)
    # end conditions: value and rate at both knots
    assert w[0] @ [ai, dai, aj, daj] == pytest.approx(ai)
    assert w[-1] @ [ai, dai, aj, daj] == pytest.approx(aj)
    h = 1e-6
    rate0 = (hermite_weights(h, dt) - hermite_weights(0.0, dt)) / (h * dt)
    assert rate0 @ [ai, dai, aj, daj] == pytest.approx(dai, rel=1e-4, abs=1e-6)


def test_line_fraction():
    whole, frac = line_fraction([0.0, 0.49, 0.5, 10.7, 99.2])
    np.testing.assert_allclose(whole, [0, 0, 1, 11, 99])
    np.testing.assert_allclose(frac, [0, 0.49, -0.5, -0.3, 0.2], atol=1e-12)


def test_detector_vector_eq2():
    alpha = np.array([0.0, 2e-4, 1e-9, 0, 0, 0])
    d = detector_vector(10.7, 800.0, 1e-4, 18e-6, 0.06, alpha, 751.5)
    s = 800.0 - 751.5
    np.testing.assert_allclose(d, [-(1e-4 + (-0.3) * 18e-6), 0.06 * (2e-4 * s + 1e-9 * s * s), 0.06], rtol=1e-12)


def test_skew():
    v, w = np.array([1.0, 2, 3]), np.array([-2.0, 0.5, 4])
    np.testing.assert_allclose(skew(v) @ w, np.cross(v, w))
