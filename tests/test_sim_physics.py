"""The simulated aircraft's physics (model.md §8), checked against independent computations:
the estimator's S and R, a KKT solve of the minimum-strain-energy split, the analytic
frequency response of the mounts, and the bus encodings of docs/bus.md §1."""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import signal, stats

from rsra.config.rig import G0, ConfigError
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.sim_bus import (
    AircraftPhysics,
    ChannelCodec,
    list_scenarios,
    load_scenario,
    quantise_sample,
    read_truth,
    simulate,
    write_truth,
)
from rsra.sim_bus.physics import SAMPLE_FIELDS, cell_axes_true, hub_matrix, wrench_matrix_true
from rsra.sim_bus.scenarios import scenario_dir

pytestmark = pytest.mark.filterwarnings("ignore::scipy.linalg.LinAlgWarning")


# ----------------------------------------------------------------------------- helpers

def kkt_split(S: np.ndarray, k: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """min sum T^2/(2k) s.t. S T = -wrench, by the KKT system (not the sim's formula)."""
    n = S.shape[1]
    A = np.block([[np.diag(1.0 / k), S.T], [S, np.zeros((6, 6))]])
    rhs = np.concatenate([np.zeros((n, wrench.shape[0])), -wrench.T])
    return np.linalg.solve(A, rhs)[:n].T


def balance_residual(model, run, frame="body") -> np.ndarray:
    """I - S(alpha_true) T - R H - W_u per sample with the ESTIMATOR's S and R."""
    R = hub_transfer_matrix(model.geometry, frame)
    res = run.I_true - run.H_true @ R.T - run.unmodelled
    uniq, inv = np.unique(run.alpha_true, axis=0, return_inverse=True)
    for j, a in enumerate(uniq):
        sel = inv.ravel() == j
        res[sel] -= run.T_true[sel] @ wrench_matrix(model.geometry, a).T
    return res


def harmonic_fit(t: np.ndarray, y: np.ndarray, omegas: list[float]) -> list[np.ndarray]:
    """Least-squares complex amplitudes c (y = Re(c e^{i w t})) at the given frequencies."""
    X = np.column_stack([f(w * t) for w in omegas for f in (np.cos, np.sin)] + [np.ones_like(t)])
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    return [coef[2 * i] - 1j * coef[2 * i + 1] for i in range(len(omegas))]


def write_scenario(tmp_path: Path, base: str, edit) -> Path:
    raw = tomllib.loads((scenario_dir() / f"{base}.toml").read_text())
    edit(raw)
    p = tmp_path / f"{base}-edited.toml"
    p.write_text(_toml(raw))
    return p


def _toml(d: dict, prefix: str = "") -> str:
    """A tiny TOML writer for the scenario tables used here."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(float(v)) if isinstance(v, float) else str(v)
    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v, False))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            tables.append((k, v, True))
        else:
            lines.append(f"{k} = {val(v)}")
    out = "\n".join(lines) + "\n"
    for k, v, many in tables:
        name = f"{prefix}{k}"
        for item in (v if many else [v]):
            head = f"[[{name}]]" if many else f"[{name}]"
            out += f"\n{head}\n" + _toml(item, name + ".")
    return out


# ----------------------------------------------------------------------------- geometry

def test_simulator_S_and_R_agree_with_estimator(model, cfg, rng):
    g = model.geometry
    for _ in range(5):
        a = rng.uniform(-0.1, 0.1, 14)
        S_sim = wrench_matrix_true(g.cell_positions, cell_axes_true(g.cell_axes, a))
        np.testing.assert_allclose(S_sim, wrench_matrix(g, a), atol=1e-12)
    for frame in ("body", "shaft"):
        R_sim = hub_matrix(cfg.hub_centre_m, cfg.shaft_tilt_rad, frame)
        np.testing.assert_allclose(R_sim, hub_transfer_matrix(g, frame), atol=1e-12)
    # a sign error would show: the shaft frame is not the body frame for a tilted shaft
    assert not np.allclose(hub_matrix(cfg.hub_centre_m, cfg.shaft_tilt_rad, "shaft"),
                           hub_matrix(cfg.hub_centre_m, cfg.shaft_tilt_rad, "body"))


def test_mount_modes_clear_of_rotor_harmonics(cfg):
    """model §8.2: six mount modes between about 35 and 155 Hz, clear of 1/rev and N_b/rev."""
    f = AircraftPhysics(cfg, "ground-test").mode_frequencies_hz()
    f_rev = cfg.rotor.omega_nominal_rad_s / (2 * np.pi)
    assert len(f) == 6 and 30.0 < f.min() and f.max() < 170.0
    assert f.min() > 2 * cfg.rotor.blades * f_rev  # the lowest mode above 2 N_b/rev


# ----------------------------------------------------------------------------- statics

def test_paper_split_is_minimum_strain_energy_every_sample(cfg, model):
    run = simulate(cfg, "paper", duration_s=5.0)
    k = np.array([c.stiffness_N_per_m for c in cfg.cells])
    R = hub_transfer_matrix(model.geometry, "body")
    S = wrench_matrix(model.geometry, run.alpha_true[0])
    T_ref = kkt_split(S, k, run.H_true @ R.T)
    scale = np.abs(T_ref).max()
    assert np.abs(run.T_true - T_ref).max() < 1e-9 * scale
    # no inertia, no gravity: the accelerometers read zero (model §8.4, `paper`)
    assert np.all(run.accel_true == 0.0) and np.all(run.I_true == 0.0)
    np.testing.assert_array_equal(run.alpha_true, 0.0)


def test_at_rest_the_dynamic_rig_settles_to_the_minimum_strain_energy_split(cfg, model, tmp_path):
    """Ground test with the shaker off: in static equilibrium at the start and, after each
    ramp, settled to the split of (hub load + weight); the CG accelerometer reads -1 g."""
    def edit(raw):
        raw["harmonics"] = []
        raw["scenario"]["noise"] = False
    sc = load_scenario(write_scenario(tmp_path, "ground-test", edit))
    run = simulate(cfg, sc, duration_s=sc.duration_s)
    k = np.array([c.stiffness_N_per_m for c in cfg.cells])
    R = hub_transfer_matrix(model.geometry, "body")
    S = wrench_matrix(model.geometry, run.alpha_true[0])
    W_g = np.concatenate([cfg.effective_mass_kg * np.array([0, 0, G0]), np.zeros(3)])
    hold = sc.loads.hold_s
    ends = np.round((np.arange(6) * hold + hold - 1.0) / run.dt).astype(int)  # 1 s before a ramp
    at_rest = np.concatenate([[0], ends])
    T_ref = kkt_split(S, k, run.H_true[at_rest] @ R.T + W_g)
    assert np.abs(run.T_true[at_rest] - T_ref).max() < 1e-6 * np.abs(T_ref).max()
    np.testing.assert_allclose(run.accel_true[at_rest, 0], np.tile([0, 0, -G0], (7, 1)), atol=1e-6)
    # the vertical cells (n = -z, positive pushes up) hold the transmission down against the
    # net lift: 80 kN of thrust less its weight (angles within 4 deg: cos 4 deg = 0.9976)
    vertical = np.abs(np.array([c.nominal_axis for c in cfg.cells])[:, 2]) > 0.9
    assert -run.T_true[0, vertical].sum() == pytest.approx(
        80000.0 - cfg.effective_mass_kg[2] * G0, rel=3e-3)


# ----------------------------------------------------------------------------- the balance

@pytest.mark.parametrize("name", ["paper", "ground-test", "flight", "sweep"])
def test_balance_holds_on_truth_every_sample(cfg, model, name):
    """I = S(alpha_true) T + R H + W_u (+ D q) exactly, with the estimator's S and R."""
    sc = load_scenario(name, angles="step", **{"angles.step_at_s": [3.0]}) \
        if name == "ground-test" else load_scenario(name)
    run = simulate(cfg, sc, duration_s=6.0 if name != "sweep" else 30.0)
    res = balance_residual(model, run)
    scale = np.abs(run.H_true).max() + np.abs(run.T_true).max()
    assert np.abs(res).max() < 1e-12 * scale * 100
    if name == "sweep":  # the unmodelled load is on and is not in any channel
        assert np.abs(run.unmodelled).max() > 100.0
        assert np.abs(balance_residual(model, run) + run.unmodelled).max() > 100.0


def test_inertial_loads_are_mass_times_specific_force(cfg):
    run = simulate(cfg, "flight", duration_s=3.0)
    np.testing.assert_allclose(run.I_true[:, :3], cfg.effective_mass_kg * run.accel_true[:, 0],
                               rtol=1e-12, atol=1e-9)
    assert run.accel_true[:, 0, 2].mean() == pytest.approx(-G0, abs=0.05)  # z down: -1 g


# ----------------------------------------------------------------------------- dynamics

def test_forced_response_matches_the_analytic_frequency_response(cfg, model):
    """Steady state at 1/rev and N_b/rev against (K - w^2 M + i w C)^-1, computed here."""
    sc = load_scenario("paper", quasi_static=False, noise=False)
    run = simulate(cfg, sc, duration_s=12.0)
    sel = run.t > 2.0  # the start-up transient of the mounts has died out
    k = np.array([c.stiffness_N_per_m for c in cfg.cells])
    beta = 2 * cfg.simulator.damping_ratio / (2 * np.pi * cfg.simulator.damping_reference_hz)
    S = wrench_matrix(model.geometry, run.alpha_true[0])
    R = hub_transfer_matrix(model.geometry, "body")
    M = np.diag(np.concatenate([cfg.effective_mass_kg, cfg.inertia_kg_m2]))
    K = S @ np.diag(k) @ S.T
    w_rev = cfg.rotor.omega_nominal_rad_s
    omegas = [w_rev, cfg.rotor.blades * w_rev]
    Hc = harmonic_fit(run.t[sel], run.H_true[sel], omegas)
    Tc = harmonic_fit(run.t[sel], run.T_true[sel], omegas)
    for w, H, T in zip(omegas, Hc, Tc):
        q = np.linalg.solve(K - w**2 * M + 1j * w * beta * K, R @ H)
        T_pred = -(k + 1j * w * beta * k) * (S.T @ q)
        T_static = -k * (S.T @ np.linalg.solve(K, R @ H))
        dyn = np.abs(T_pred - T_static).max()
        assert dyn > 1e-3 * np.abs(T_pred).max()  # the dynamic part is really there
        assert np.abs(T - T_pred).max() < 0.01 * dyn


def test_base_vibration_reaches_the_cells_as_the_analytic_transmissibility(cfg, model, tmp_path):
    """Cell forces per unit base acceleration (MIMO H1 estimate over the three base axes,
    noise-free) against -(k + i w c) s^T ((K - w^2 M + i w C)^-1 (K + i w C) - I) d."""
    def edit(raw):
        raw["harmonics"], raw["manoeuvres"] = [], []
        raw["scenario"]["noise"] = False
        raw["angles"]["mode"] = "constant"
    run = simulate(cfg, load_scenario(write_scenario(tmp_path, "flight", edit)), duration_s=60.0)
    a, y, fs = run.base_accel, run.T_true, 1.0 / run.dt
    def csd(u, v):  # E[conj(U) V]
        return signal.csd(u, v, fs, nperseg=1024)

    f = csd(a[:, 0], a[:, 0])[0]
    P_aa = np.array([[csd(a[:, i], a[:, j])[1] for j in range(3)] for i in range(3)])
    P_ay = np.array([[csd(a[:, i], y[:, j])[1] for j in range(7)] for i in range(3)])
    k = np.array([c.stiffness_N_per_m for c in cfg.cells])
    beta = 2 * cfg.simulator.damping_ratio / (2 * np.pi * cfg.simulator.damping_reference_hz)
    S = wrench_matrix(model.geometry, run.alpha_true[0])
    M = np.diag(np.concatenate([cfg.effective_mass_kg, cfg.inertia_kg_m2]))
    K = S @ np.diag(k) @ S.T
    E3 = np.vstack([np.eye(3), np.zeros((3, 3))])  # base translation in generalised coordinates
    for f_hz in (8.0, 12.0, 16.0, 20.0, 25.0, 30.0):
        j = np.argmin(np.abs(f - f_hz))
        w = 2 * np.pi * f[j]
        H = np.linalg.solve(P_aa[:, :, j], P_ay[:, :, j]).T  # (7 cells, 3 base axes)
        G = np.linalg.solve(K - w**2 * M + 1j * w * beta * K, (K + 1j * w * beta * K) @ E3)
        H_pred = -(k + 1j * w * beta * k)[:, None] * (S.T @ (G - E3)) / -(w**2)  # d = -a / w^2
        assert np.abs(H - H_pred).max() < 0.02 * np.abs(H_pred).max(), f_hz


def test_spectra_show_the_configured_harmonics(cfg):
    sc = load_scenario("ground-test")
    phys = AircraftPhysics(cfg, sc)
    run = simulate(cfg, sc, duration_s=9.0)  # inside the first hold: constant static load
    f = np.fft.rfftfreq(len(run), run.dt)
    f_rev = cfg.rotor.omega_nominal_rad_s / (2 * np.pi)
    peaks = [f_rev, cfg.rotor.blades * f_rev]
    bands = [np.abs(f - p) < 0.5 for p in peaks]
    elsewhere = ~np.logical_or(*bands) & (f > 0.5)
    win = np.hanning(len(run))
    for series in (run.H_true, run.T_true):
        spec = np.abs(np.fft.rfft((series - series.mean(0)) * win[:, None], axis=0))
        for band in bands:  # every component and every cell shows both harmonics
            assert np.all(spec[band].max(0) > 30 * spec[elsewhere].max(0))
    # amplitudes within the configured ranges (times the slow variation)
    c = harmonic_fit(run.t, run.H_true, [2 * np.pi * p for p in peaks])
    for j, h in enumerate(sc.harmonics):
        amp = np.abs(c[j])
        assert np.all(amp >= h.amplitude_min * (1 - h.amplitude_variation) * 0.98)
        assert np.all(amp <= h.amplitude_max * (1 + h.amplitude_variation) * 1.02)
        np.testing.assert_allclose(amp, phys.harm_amp[j], rtol=1.5 * h.amplitude_variation)


def test_paper_harmonics_are_exactly_the_drawn_ones(cfg):
    sc = load_scenario("paper", noise=False)
    phys = AircraftPhysics(cfg, sc)
    run = simulate(cfg, sc, duration_s=5.0)
    w = cfg.rotor.omega_nominal_rad_s
    c = harmonic_fit(run.t, run.H_true, [w, cfg.rotor.blades * w])
    for j in range(2):
        np.testing.assert_allclose(np.abs(c[j]), phys.harm_amp[j], rtol=1e-9)
        np.testing.assert_allclose(np.angle(c[j] * np.exp(-1j * phys.harm_phase[j])), 0, atol=1e-9)


def test_base_vibration_and_rotor_speed_in_flight(cfg):
    sc = load_scenario("flight")
    run = simulate(cfg, sc, duration_s=60.0)
    rms = run.base_accel.std(0) / G0
    np.testing.assert_allclose(rms, sc.base_vibration.rms_g, rtol=0.15)
    spec = np.abs(np.fft.rfft(run.base_accel[:, 2])) ** 2
    f = np.fft.rfftfreq(len(run), run.dt)
    lo, hi = sc.base_vibration.band_hz
    assert spec[(f > lo) & (f < hi)].sum() > 0.8 * spec.sum()
    w0 = cfg.rotor.omega_nominal_rad_s
    assert np.all(np.abs(run.omega / w0 - 1) <= sc.rotor.omega_variation + 1e-6)
    assert np.ptp(run.omega) > sc.rotor.omega_variation * w0  # it does vary
    # the azimuth advances by the rotor speed (trapezoid of Omega over one sample)
    dpsi = np.diff(np.unwrap(run.azimuth))
    np.testing.assert_allclose(dpsi, 0.5 * (run.omega[1:] + run.omega[:-1]) * run.dt, atol=2e-4)


def test_unmodelled_load_is_proportional_with_phase(cfg):
    run = simulate(cfg, "sweep", duration_s=100.0)  # X sweeps, then Y
    assert np.abs(run.H_true[:, 0]).max() > 800.0 and np.abs(run.H_true[:, 1]).max() > 800.0
    np.testing.assert_allclose(run.unmodelled[:, 3], -0.3 * run.H_true[:, 1], atol=1e-9)
    np.testing.assert_allclose(run.unmodelled[:, 0], -0.1 * run.H_true[:, 0], atol=1e-9)
    assert np.all(run.unmodelled[:, [1, 2, 4, 5]] == 0)
    # another phase: the complex ratio at each harmonic is gain e^{i phase}
    sc = load_scenario("paper", unmodelled=True, noise=False, **{"unmodelled.phase_deg": 60.0})
    run = simulate(cfg, sc, duration_s=5.0)
    w = cfg.rotor.omega_nominal_rad_s
    cY = harmonic_fit(run.t, run.H_true[:, 1], [w, 5 * w])
    cL = harmonic_fit(run.t, run.unmodelled[:, 3], [w, 5 * w])
    for y, l_ in zip(cY, cL):
        assert l_ / y == pytest.approx(0.3 * np.exp(1j * math.radians(60.0)), abs=1e-9)


# ----------------------------------------------------------------------------- true angles

def test_true_angles_constant_step_and_linear(cfg):
    gt = simulate(cfg, "ground-test", duration_s=2.0)
    assert np.all(gt.alpha_true == gt.alpha_true[0])
    assert np.abs(gt.alpha_true[0]).max() <= math.radians(4.0)
    assert np.abs(gt.alpha_true[0]).max() > math.radians(1.0)  # drawn, not zero

    sc = load_scenario("ground-test", angles="step", **{"angles.step_at_s": [1.0]})
    st = simulate(cfg, sc, duration_s=2.0)
    i = round(1.0 / st.dt)
    np.testing.assert_array_equal(st.alpha_true[:i], gt.alpha_true[:i])  # same seed, same base
    step = st.alpha_true[i] - st.alpha_true[i - 1]
    np.testing.assert_allclose(np.abs(step), math.radians(1.0), rtol=1e-12)
    assert 0 < (step > 0).sum() < 14  # random signs
    assert np.all(st.alpha_true[i:] == st.alpha_true[i])

    sc = load_scenario("ground-test", angles="linear")
    phys = AircraftPhysics(cfg, sc)
    lin = simulate(cfg, sc, duration_s=25.0)
    static = np.array([phys.loads._static(np.array([t]))[0] for t in lin.t[::50]])
    pred = phys.alpha_base + static @ phys.alpha_gain.T
    res = sc.angles.resolution_rad
    assert np.abs(lin.alpha_true[::50] - pred).max() <= res / 2 + 1e-15
    thrust_deg = np.degrees(np.abs(lin.alpha_true - phys.alpha_base).max())
    assert thrust_deg == pytest.approx(0.84, abs=0.01)  # 1 deg per 100 kN, 84 kN


def test_ground_test_and_flight_fly_the_same_aircraft_for_a_seed(cfg):
    """Calibrate on the ground, fly with that posterior (issue 14): for a given seed every
    scenario with random base angles has the same base angles, whatever else it draws (here a
    flight with a third harmonic and no manoeuvres draws other parameters in between)."""
    from rsra.sim_bus.scenarios import parse_scenario

    raw = tomllib.loads((scenario_dir() / "flight.toml").read_text())
    raw["harmonics"].append(dict(raw["harmonics"][0], order=2))
    raw.pop("manoeuvres")
    other = parse_scenario(raw)
    bases = []
    for seed in (1, 7, 1301, 1401):
        a = [AircraftPhysics(cfg, sc, seed=seed).alpha_base
             for sc in (load_scenario("ground-test"), load_scenario("flight"), other)]
        np.testing.assert_array_equal(a[0], a[1])
        np.testing.assert_array_equal(a[0], a[2])
        assert np.abs(a[0]).max() <= math.radians(4.0)
        bases.append(a[0])
    assert not np.array_equal(bases[0], bases[1])  # another seed, another aircraft
    # the flight's true angles are those base angles moved with the static load
    fl = simulate(cfg, "flight", duration_s=1.0, seed=7)
    gt = simulate(cfg, "ground-test", duration_s=1.0, seed=7)
    assert np.all(gt.alpha_true == AircraftPhysics(cfg, "flight", seed=7).alpha_base)
    drift = np.degrees(np.abs(fl.alpha_true - gt.alpha_true[0]).max())
    assert 0.5 < drift < 1.5  # about 1° per 100 kN of thrust (trim 95 kN)


# ----------------------------------------------------------------------------- determinism

def test_same_seed_identical_other_seed_different(cfg):
    a = simulate(cfg, "flight", n_samples=600)
    b = simulate(cfg, "flight", n_samples=600)
    c = simulate(cfg, "flight", n_samples=600, seed=7)
    for name, v in a.arrays().items():
        assert np.array_equal(v, getattr(b, name)), name
    assert not np.array_equal(a.T, c.T) and not np.array_equal(a.alpha_true, c.alpha_true)
    assert a.meta["seed"] == load_scenario("flight").seed


@pytest.mark.parametrize("name", ["flight", "sweep"])
def test_streaming_equals_offline_bit_for_bit(cfg, name):
    sc = load_scenario(name)
    phys = AircraftPhysics(cfg, sc, block_size=200)
    codec = ChannelCodec(cfg)
    streamed = [quantise_sample(phys.next_sample(), codec) for _ in range(500)]
    run = simulate(cfg, sc, n_samples=500, block_size=200)
    assert [s.index for s in streamed] == list(range(500)) and phys.index == 500
    for f in SAMPLE_FIELDS:
        assert np.array_equal(np.array([getattr(s, f) for s in streamed]), getattr(run, f)), f


def test_blocks_computed_ahead_by_another_thread_are_the_streamed_ones(cfg):
    """compute_ahead (a real-time driver's thread, outside the simulator's lock) gives the
    samples of plain streaming bit for bit, whenever it runs within a block."""
    import threading

    sc = load_scenario("flight")
    ref = AircraftPhysics(cfg, sc, block_size=50)
    want = [ref.next_sample() for _ in range(260)]
    phys = AircraftPhysics(cfg, sc, block_size=50)
    got, computed = [], []
    for i in range(260):
        if i % 7 == 3:  # at different positions within the blocks, from another thread
            th = threading.Thread(target=lambda: computed.append(phys.compute_ahead()))
            th.start()
            got.append(phys.next_sample())
            th.join()
        else:
            got.append(phys.next_sample())
    assert any(computed) and not all(computed)  # computed ahead once per block at most
    assert [s.index for s in got] == list(range(260))
    for f in SAMPLE_FIELDS:
        assert np.array_equal(np.array([getattr(s, f) for s in got]),
                              np.array([getattr(s, f) for s in want])), f


# ----------------------------------------------------------------------------- channels

def test_sensor_noise_is_accuracy_times_full_scale(cfg):
    run = simulate(cfg, "ground-test", duration_s=20.0)
    n = len(run)
    checks = [(run.T - run.T_true, np.array([c.full_scale_N * c.accuracy_fs for c in cfg.cells])),
              (run.H_balance - run.H_true, cfg.balance.sigma)]
    acc = cfg.accelerometers[0]
    checks.append(((run.accel - run.accel_true)[:, 0],
                   np.full(3, acc.full_scale_g * G0 * acc.accuracy_fs)))
    n_tests = sum(len(s) for _, s in checks)
    lo, hi = stats.chi2.ppf([1e-3 / n_tests / 2, 1 - 1e-3 / n_tests / 2], n - 1) / (n - 1)
    for err, sigma in checks:
        # the REAL32 / 1 mg quantisation adds (lsb^2/12): negligible against these sigmas
        ratio = err.var(axis=0, ddof=1) / sigma**2
        assert np.all((ratio > lo) & (ratio < hi)), ratio
    quiet = simulate(cfg, load_scenario("paper", noise=False), duration_s=1.0)
    np.testing.assert_array_equal(quiet.T, quiet.T_true.astype(np.float32).astype(float))


def test_channels_are_quantised_as_the_bus_encodes_them(cfg):
    sc = load_scenario("flight")
    phys = AircraftPhysics(cfg, sc, block_size=200)
    raw = [phys.next_sample() for _ in range(200)]
    run = simulate(cfg, sc, n_samples=200, block_size=200)
    T = np.array([s.T for s in raw])
    np.testing.assert_array_equal(run.T, T.astype(np.float32).astype(np.float64))
    acc = np.array([s.accel for s in raw])
    np.testing.assert_array_equal(run.accel_counts, np.rint(acc / (G0 * 1e-3)).astype(np.int16))
    np.testing.assert_allclose(run.accel, acc, atol=G0 * 1e-3 / 2 + 1e-12)
    assert run.accel_counts[:, 0, 2].mean() == pytest.approx(-1000, abs=5)  # z reads -1000 mg
    az = np.array([s.azimuth for s in raw])
    assert np.all((az >= 0) & (az < 2 * np.pi))
    np.testing.assert_allclose(run.azimuth, az, atol=np.pi / 65536 + 1e-12)
    codec = ChannelCodec(cfg)
    enc = codec.encode(T=np.zeros(7), cell_status=np.zeros(7),
                       accel=np.array([[100.0, -100.0, 5.0]]), omega=19.4,
                       azimuth=2 * np.pi - 1e-9, H_balance=np.zeros(6), drive=np.zeros(0))
    fs = cfg.accelerometers[0].full_scale_g * 1000
    np.testing.assert_array_equal(enc.accel_counts, [[fs, -fs, 510]])  # saturates at full scale
    assert enc.accel_counts.dtype == np.int16 and enc.azimuth_counts == 0  # 2 pi wraps to 0


def test_over_range_sets_status_bit(cfg, tmp_path):
    def edit(raw):
        raw["loads"]["conditions"] = [[0.0, 0.0, -600000.0, 0.0, 0.0, 0.0]] * 6
    run = simulate(cfg, load_scenario(write_scenario(tmp_path, "ground-test", edit)), n_samples=50)
    fs = np.array([c.full_scale_N for c in cfg.cells])
    np.testing.assert_array_equal(run.cell_status & 1, (np.abs(run.T) > fs).astype(np.uint8))
    assert run.cell_status[:, :4].all() and not run.cell_status[:, 4:].any()


# ----------------------------------------------------------------------------- scenarios

def test_every_packaged_scenario_loads():
    names = list_scenarios()
    assert {"paper", "ground-test", "flight", "sweep"} <= set(names)
    for n in names:
        sc = load_scenario(n)
        assert sc.name == n and sc.duration_s > 0 and sc.seed >= 0
    assert load_scenario("paper").rig_overrides["identification"]["initial_angles_deg"] == 4.0
    sw = load_scenario("sweep")
    assert sw.unmodelled.enabled and sw.shaker.cycle_s <= sw.duration_s
    assert sw.shaker.levels[0] == pytest.approx(200 * 4.4482216152605)
    assert load_scenario("ground-test", angles="linear").angles.mode == "linear"
    assert load_scenario("paper", noise=False).noise is False


@pytest.mark.parametrize("edit, key", [
    (lambda r: r["angles"].__setitem__("mode", "stepp"), "angles.mode"),
    (lambda r: r["loads"].__setitem__("ramp_sec", 0.5), "loads.ramp_sec"),
    (lambda r: r["harmonics"][0].__setitem__("amplitude_min", [1.0, 2.0]),
     "harmonics[0].amplitude_min"),
    (lambda r: r["scenario"].pop("duration_s"), "scenario.duration_s"),
    (lambda r: r["loads"].__setitem__("hold_s", 7.0), "loads.hold_s"),
    (lambda r: r["base_vibration"].__setitem__("enabled", "yes"), "base_vibration.enabled"),
])
def test_bad_scenario_gives_a_clear_error(tmp_path, edit, key):
    p = write_scenario(tmp_path, "ground-test", edit)
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    assert e.value.key == key and p.name in str(e.value) and "fix:" in str(e.value)


def test_bad_names_and_variants_give_clear_errors():
    with pytest.raises(ConfigError, match="no such scenario.*ground-test"):
        load_scenario("groundtest")
    with pytest.raises(ConfigError, match="unknown variant"):
        load_scenario("paper", nosie=False)
    with pytest.raises(ConfigError, match=r"angles\.mode.*did you mean"):
        load_scenario("paper", angles="lineer")
    with pytest.raises(ConfigError, match="quasi-static"):
        load_scenario("paper", base_vibration=True)


# ----------------------------------------------------------------------------- truth

def test_truth_file_round_trip(cfg, tmp_path):
    run = simulate(cfg, "sweep", n_samples=300)
    faults = [{"kind": "stuck", "node": "cell_A", "start_index": 10, "end_index": 20}]
    p = write_truth(tmp_path / "run1", run, faults=faults, meta={"note": "test"})
    d = read_truth(p)
    assert p.suffix == ".npz" and d["faults"] == faults
    assert d["meta"]["scenario"] == "sweep" and d["meta"]["note"] == "test"
    assert d["meta"]["angle_names"][:2] == ["delta_A", "theta_A"]
    assert d["meta"]["angle_names"][-2:] == ["theta_G", "psi_G"]
    for name, v in run.arrays().items():
        assert np.array_equal(d[name], v), name
    np.testing.assert_array_equal(d["sync_counter"][:3], [1, 2, 3])
    assert d["sync_counter"][240] == 1 and d["sync_counter"].max() == 240
    with pytest.raises(ValueError, match="samples"):
        write_truth(tmp_path / "bad", {"index": np.arange(3), "t": np.zeros(3),
                                       "H_true": np.zeros((2, 6)), "alpha_true": np.zeros((3, 14)),
                                       "T_true": np.zeros((3, 7))})
