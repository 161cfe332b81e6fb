"""When the angles are not constant: competing structures of the known-load model and a
sequential test of the constant-angle model against them (docs/identification.md,
"When the angles are not constant: the structure test").

The known-load balance is ``z = S(α) T + R₀ H (+ E q)``; its residual at the constant-angle
model is ``r = z − S(α) T − R₀ H − E q``. Each competing structure adds a term that is zero at
β = 0 and predicts, for the same measured (z, T, H), a model ``m(α, β; T, H)``:

* ``cell_load_angles`` — every angle moves with the load its own cell carries,
  ``α_k = α0_k + g_k T_c(k)`` (14 gains, rad/N: a compliance-like gain per angle; the rigid-body
  model has no link length, so this is what a deflecting transmission can be identified as);
* ``hub_position`` — the hub centre is off by δp (3, m): ``R(p_H + δp)``;
* ``balance`` — the reference balance has per-axis scale errors s (6) and an alignment error φ
  (3, rad): the true hub load is ``[(I + skew φ)(1 + s_F)∘F_b; (I + skew φ)(1 + s_M)∘M_b]``;
* ``external_load`` — an unmodelled load path: a CG wrench linear in the applied hub forces,
  ``U F`` (6×3, N or N·m per N; the report's Phase I roll torque ∝ Y and x-force ∝ X).

**The interface for the experiment design** (another module chooses the next load conditions):
everything the structures are is in three pure functions of (model, α, mean data), no state:
:func:`parameter_names` (names and units), :func:`angle_jacobian` (``∂m/∂α``, 6×14 for one
condition) and :func:`structure_jacobian` (``∂m/∂β`` at β = 0, 6×p for one condition, given
the condition's mean ``x̄ = [z, T, H, q]``; T can be predicted for a planned condition by the
minimum-strain-energy split). The information of a design about (α, β) is
``Σ_c n_c [J_α J_β]ᵀ W⁻¹ [J_α J_β]`` over its conditions; :func:`design_ranks` gives, per
structure, the rank of β left after the angles (the testable directions) and which structures
a design cannot separate.

The test (:class:`StructureTest`): static known-load windows are summarised by their means; a
window of n scored samples has a mean residual of covariance W(α)/n (W the effective-variance
weight of model §7; the static content filter has unit gain at DC). Windows at the same load
(within ``cluster_tolerance``) are pooled: every structure predicts the same residual at the
same load, so pooling loses nothing. At every look (every known-load window):

1. *a change in time* — the new window's mean residual against its cluster's earlier windows
   (χ²₆; the same load, so the difference does not depend on any structure): significant at
   ``time_level`` (10⁻³ per window) restarts the accumulation from this window (a step in the
   angles, the tracking benchmark, is a change in time, not a load dependence);
2. the constant-angle model is fitted to the cluster means (Gauss–Newton on the 14 angles,
   pseudo-inverse: directions the design does not determine stay where they are);
3. for each structure s, its whitened Jacobian is projected off the angles' span; the rank
   r_s of what is left (singular values above ``RANK_TOLERANCE`` of the largest) is the
   number of testable directions. The likelihood-ratio statistic of the linearised model,
   ``q_s = ‖U_sᵀ ê‖²`` (ê the whitened residual of the constant fit, U_s the left singular
   vectors kept), is χ²_{r_s} under constant angles;
4. the constant model is rejected at look k when some ``q_s > χ²_{r_s}(1 − a_k/S)``, with the
   alpha-spending rule ``a_k = A · 6/(π² k²)`` (Σ a_k = A = 10⁻³ over any number of looks;
   Bonferroni over the S structures): the false-alarm rate of saying ``not_constant`` at any
   time of the run is at most A, whatever the dependence between looks. Once rejected, the
   verdict stays ``not_constant`` until a change in time restarts the accumulation.

Candidates are ranked: those whose remaining misfit passes at the same level ("explains the
data") first, then by the p-value of q_s (a smaller structure that explains as much ranks
before a larger one that contains it). Each carries the fitted parameters, their σ, the same
per kN of load, and the statistic. The estimate and the misfit come from the joint fit of
[α0, β] (:func:`fit_structure`: Levenberg–Marquardt with the analytic Jacobian, in the
directions the conditions determine only — the others stay at the prior and are reported as
not determined). A structure is *selected* for the hub loads (``StructureVerdict.selected``)
only when it explains the data, is determined, its fit converged and determines the hub loads
(:func:`hub_sigma`), and every other explaining structure contains it by construction
(``NESTED``) or is tested and fits worse; :class:`StructureCorrection` is that structure in
the form the per-sample hub-load path applies.

Where each part lives: the structures (a registry, :data:`STRUCTURES`) in
estimator.structures; their shared numerics in estimator.structure_fits; the structure test in
estimator.structure_test; the drift test in estimator.drift_test. This module names them all
(the imports of the package and its users stay as they were). Pure numerics.
"""
from __future__ import annotations

from .structure_fits import (  # noqa: F401  (re-exported)
    VERDICTS as VERDICTS,
    DRIFTING as DRIFTING,
    MAX_DRIFT_WINDOWS as MAX_DRIFT_WINDOWS,
    DRIFT_BOUND_LEVEL as DRIFT_BOUND_LEVEL,
    MAX_HELD_LOOKS as MAX_HELD_LOOKS,
    NESTED as NESTED,
    FALSE_ALARM as FALSE_ALARM,
    TIME_LEVEL as TIME_LEVEL,
    RANK_TOLERANCE as RANK_TOLERANCE,
    CLUSTER_TOLERANCE as CLUSTER_TOLERANCE,
    MAX_CLUSTERS as MAX_CLUSTERS,
    MAX_PARAMETERS_REPORTED as MAX_PARAMETERS_REPORTED,
    GN_ITERATIONS as GN_ITERATIONS,
    HUB_SIGMA_FRACTION as HUB_SIGMA_FRACTION,
    FIT_TOLERANCE as FIT_TOLERANCE,
    FIT_MAX_EVALUATIONS as FIT_MAX_EVALUATIONS,
    CONVERGED_STEP_RAD as CONVERGED_STEP_RAD,
    parameter_names as parameter_names,
    parameter_units as parameter_units,
    per_kN as per_kN,
    _split as _split,
    residual as residual,
    structure_residual as structure_residual,
    angle_jacobian as angle_jacobian,
    structure_jacobian as structure_jacobian,
    structure_matrices as structure_matrices,
    hub_loads as hub_loads,
    _whitener as _whitener,
    _batched as _batched,
    _stack as _stack,
    _white_residual as _white_residual,
    _unit_columns as _unit_columns,
    _range_basis as _range_basis,
    _cell_columns as _cell_columns,
    _white_jacobian as _white_jacobian,
    StructureEstimate as StructureEstimate,
    fit_structure as fit_structure,
    hub_sigma as hub_sigma,
    fit_constant as fit_constant,
    fit_constant_converged as fit_constant_converged,
    settle_constant as settle_constant,
    constant_misfit as constant_misfit,
    StructureFit as StructureFit,
    test_structures as test_structures,
    design_ranks as design_ranks,
    spend as spend,
    APPLIED as APPLIED,
    fit_payload as fit_payload,
    check_fit_payload as check_fit_payload,
    StructureCorrection as StructureCorrection,
    AXES as AXES,
    STRUCTURES as STRUCTURES,
    Structure as Structure,
    structure_of as structure_of,
)
from .drift_test import (  # noqa: F401  (re-exported)
    DriftVerdict as DriftVerdict,
    rate_scale_bound as rate_scale_bound,
    _trend_prediction as _trend_prediction,
    _Refit as _Refit,
    DriftTest as DriftTest,
)
from .structure_test import (  # noqa: F401  (re-exported)
    _Cluster as _Cluster,
    StructureVerdict as StructureVerdict,
    StructureTest as StructureTest,
)
