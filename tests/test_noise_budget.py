"""Model §4: the noise budget against a Monte Carlo of the static estimate, and the CLI."""
import json
import subprocess
import sys

import numpy as np

from rsra.estimator.balance import inertial_loads, static_estimate
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.noise_budget import noise_budget


def test_monte_carlo_matches_budget(model):
    """20 000 draws; the sample sigma of each axis has relative s.e. 1/sqrt(2N) = 0.5 %,
    so 3 % is a 6-sigma band: a correct budget never fails, a 3 % error always does."""
    rng = np.random.default_rng(7)
    N = 20000
    a = np.zeros(14)
    S = wrench_matrix(model.geometry, a)
    R = hub_transfer_matrix(model.geometry)
    H = np.array([1e3, -2e3, -8e4, 5e3, 4e3, -3e3])
    f_true = np.array([0.0, 0.0, -9.80665])
    I_true = inertial_loads(model, np.tile(f_true, (1, 1, 1)))[0]
    T_true = np.linalg.lstsq(S, I_true - R @ H, rcond=None)[0]
    K = model.accelerometers.positions.shape[0]
    T = T_true + rng.normal(size=(N, 7)) * model.cell_sigma
    acc = f_true + rng.normal(size=(N, K, 3)) * model.accelerometers.sigma[None, :, None]
    Hh = static_estimate(model, a, T, inertial_loads(model, acc))
    sig_mc = Hh.std(axis=0, ddof=1)
    nb = noise_budget(model, a)
    np.testing.assert_allclose(sig_mc, nb.total, rtol=0.03)
    np.testing.assert_allclose(np.sqrt(nb.load_cells**2 + nb.accelerometers**2), nb.total, rtol=1e-12)
    assert np.abs(Hh.mean(axis=0) - H).max() < 5 * nb.total.max() / np.sqrt(N)


def test_cli_json_contract():
    out = subprocess.run([sys.executable, "-m", "rsra", "noise-budget", "--json"],
                         capture_output=True, text=True, check=True).stdout
    d = json.loads(out)
    assert set(d) == {"units", "axes", "total", "load_cells", "accelerometers"}
    assert d["axes"] == ["X", "Y", "Z", "L", "M", "N"]
    assert d["units"][:3] == ["N"] * 3
    us = json.loads(subprocess.run([sys.executable, "-m", "rsra", "noise-budget", "--json",
                                    "--units", "us"], capture_output=True, text=True,
                                   check=True).stdout)
    np.testing.assert_allclose(np.array(us["total"][:3]) * 4.4482216152605, d["total"][:3])
    np.testing.assert_allclose(np.array(us["total"][3:]) * 1.3558179483314004, d["total"][3:])


def test_cli_table_names_every_axis():
    out = subprocess.run([sys.executable, "-m", "rsra", "noise-budget"], capture_output=True,
                         text=True, check=True, env={"COLUMNS": "120", "PATH": ""}).stdout
    for ax in "XYZLMN":
        assert f" {ax} " in out
