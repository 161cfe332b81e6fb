"""The structures as a registry (estimator/structures.py): a new structure is one subclass and
one entry in STRUCTURES, and every function of estimator.structure that takes a structure's
name reaches it through that table."""
from __future__ import annotations

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.estimator import structure as st
from rsra.estimator.structures import STRUCTURES, Structure, structure_of


class HubScale(Structure):
    """A made-up structure: the hub forces read with one common scale error s."""

    name = "hub_scale"

    def parameter_names(self, model):
        return ("hub_scale",)

    def parameter_units(self, model):
        return ("N/kN",)

    def predict(self, model, alpha, beta, T, H):
        return super().predict(model, alpha, np.zeros(0), T, H * np.r_[[1 + beta[0]] * 3,
                                                                         [1.0] * 3])

    def jacobian(self, model, dS, T, H):
        R0 = super().matrices(np.zeros(0), model)["R"]
        return np.einsum("ab,nb->na", R0[:, :3], H[:, :3])[:, :, None]


@pytest.fixture(scope="module")
def model():
    return load_config().rig_model()


def test_a_new_structure_is_one_class_and_one_entry(monkeypatch, model):
    monkeypatch.setitem(STRUCTURES, "hub_scale", HubScale())
    rng = np.random.default_rng(3)
    n = model.geometry.n_cells
    alpha = rng.normal(0, 0.01, 2 * n)
    xbar = np.concatenate([rng.normal(0, 100, 6), rng.normal(0, 1e3, n), rng.normal(0, 1e3, 6)])
    assert st.parameter_names("hub_scale", model) == ("hub_scale",)
    J = st.structure_jacobian("hub_scale", model, alpha, xbar)
    h = 1e-6
    fd = -(st.structure_residual("hub_scale", model, alpha, np.r_[h], xbar)
           - st.structure_residual("hub_scale", model, alpha, np.r_[-h], xbar)) / (2 * h)
    np.testing.assert_allclose(J[:, 0], fd, rtol=1e-6, atol=1e-6)
    # the linearised test sees it beside the others
    means = np.array([xbar, xbar * np.r_[[1.0] * 6, [1.0] * n, [2.0] * 6]])
    r = st.design_ranks(model, alpha, means, structures=("hub_scale", "hub_position"))
    assert r["nominal"]["hub_scale"] == 1


def test_the_table_names_every_structure_and_refuses_others(model):
    assert tuple(STRUCTURES) == ("cell_load_angles", "hub_position", "balance", "external_load")
    assert all(s.name == k for k, s in STRUCTURES.items())
    with pytest.raises(ValueError, match="unknown structure 'nope'; choose from"):
        structure_of("nope")
    with pytest.raises(ValueError, match="unknown structure"):
        st.parameter_names("nope", model)
