"""Model §2–§3: cell axes, S, dS/dalpha, R, inertial loads and the static estimate."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rsra.estimator.balance import (
    accel_solution_matrix,
    balance_residual,
    inertial_loads,
    static_estimate,
)
from rsra.estimator.geometry import (
    cell_axes,
    hub_transfer_matrix,
    shaft_rotation,
    wrench_matrix,
    wrench_matrix_jacobian,
)
from rsra.estimator.params import Accelerometers


def test_angle_order_is_the_contract(model):
    assert model.geometry.angle_names == (
        "delta_A", "theta_A", "delta_B", "theta_B", "delta_C", "theta_C", "delta_D", "theta_D",
        "delta_E", "psi_E", "delta_F", "psi_F", "theta_G", "psi_G")


def test_expanded_axes_match_eq_A2(model):
    """The closed forms of model.md §2 (for n = z, y, x) against the rotation code."""
    rng = np.random.default_rng(1)
    a = rng.uniform(-0.1, 0.1, 14)
    u = cell_axes(model.geometry, a)
    d, t = a[0], a[1]
    # vertical cells have n = -z: every component changes sign
    np.testing.assert_allclose(u[0], -np.array([np.cos(d) * np.sin(t), -np.sin(d), np.cos(d) * np.cos(t)]))
    d, p = a[8], a[9]
    np.testing.assert_allclose(u[4], [-np.cos(d) * np.sin(p), np.cos(d) * np.cos(p), np.sin(d)])
    t, p = a[12], a[13]
    np.testing.assert_allclose(u[6], [np.cos(t) * np.cos(p), np.cos(t) * np.sin(p), -np.sin(t)])


def test_axes_against_scipy_rotation(model):
    rng = np.random.default_rng(2)
    a = rng.uniform(-0.2, 0.2, 14)
    u = cell_axes(model.geometry, a)
    seq = {"vertical": "xy", "lateral": "xz", "longitudinal": "yz"}
    for i, kind in enumerate(model.geometry.cell_kinds):
        r = Rotation.from_euler(seq[kind], [a[2 * i], a[2 * i + 1]])  # extrinsic: first, then second
        np.testing.assert_allclose(u[i], r.apply(model.geometry.cell_axes[i]), atol=1e-14)


@pytest.mark.parametrize("seed", range(5))
def test_dS_against_central_differences(model, seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.1, 0.1, 14)
    dS = wrench_matrix_jacobian(model.geometry, a)
    h = 1e-6
    for j in range(14):
        e = np.zeros(14)
        e[j] = h
        fd = (wrench_matrix(model.geometry, a + e) - wrench_matrix(model.geometry, a - e)) / (2 * h)
        err = np.abs(fd - dS[j]).max() / np.abs(dS[j]).max()
        assert err <= 1e-7, (j, err)
        # only the column of the angle's own cell moves
        others = np.delete(np.arange(7), j // 2)
        assert np.all(dS[j][:, others] == 0)


def test_R_shaft_tilt_sign(model):
    """A 2 deg forward tilt turns the shaft's thrust axis -z to (sin 2deg, 0, -cos 2deg)."""
    C = shaft_rotation(model.geometry, "shaft")
    t = model.geometry.shaft_tilt_rad
    np.testing.assert_allclose(C @ [0, 0, -1.0], [np.sin(t), 0, -np.cos(t)], atol=1e-15)
    R = hub_transfer_matrix(model.geometry, "body")
    # a pure force at the hub makes the moment p_H x F at the CG, yaw term h_x*Y kept
    F = np.array([0.0, 1000.0, 0.0])
    w = R @ np.concatenate([F, np.zeros(3)])
    np.testing.assert_allclose(w[3:], np.cross(model.geometry.hub_position, F))
    assert w[5] == pytest.approx(model.geometry.hub_position[0] * 1000.0)


def test_static_estimate_recovers_H_noise_free(model):
    rng = np.random.default_rng(3)
    a = np.radians(rng.uniform(-4, 4, 14))
    N = 500
    H = rng.normal(0, 2e4, (N, 6))
    I = rng.normal(0, 3e3, (N, 6))
    S = wrench_matrix(model.geometry, a)
    R = hub_transfer_matrix(model.geometry)
    # any T that satisfies the balance: min-norm solution of S T = I - R H
    T = np.linalg.lstsq(S, (I - H @ R.T).T, rcond=None)[0].T
    Hh = static_estimate(model, a, T, I)
    np.testing.assert_allclose(Hh, H, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    assert np.abs(balance_residual(model, a, T, I, H)).max() < 1e-6


def test_inertial_loads_least_squares_three_triaxes(model):
    rng = np.random.default_rng(4)
    pos = np.array([[0.5, 0.0, 0.0], [0.0, 0.6, 0.0], [0.0, 0.0, 0.7]])
    acc = Accelerometers(positions=pos, sigma=np.ones(3), angular="least_squares")
    f = rng.normal(size=3)
    wd = rng.normal(size=3)
    read = np.array([f + np.cross(wd, r) for r in pos])
    sol = accel_solution_matrix(acc) @ read.ravel()
    np.testing.assert_allclose(sol, np.concatenate([f, wd]), atol=1e-12)
    # collinear points cannot give the angular acceleration
    bad = Accelerometers(positions=np.array([[0, 0, 0], [1.0, 0, 0]]), sigma=np.ones(2),
                         angular="least_squares")
    with pytest.raises(ValueError, match="non-collinear"):
        accel_solution_matrix(bad)


def test_inertial_loads_neglect_is_mass_times_specific_force(model):
    f = np.array([[0.1, -0.2, -9.80665]])
    I = inertial_loads(model, f[:, None, :])
    np.testing.assert_allclose(I[0, :3], model.mass.mass * f[0])
    np.testing.assert_allclose(I[0, 3:], 0)
