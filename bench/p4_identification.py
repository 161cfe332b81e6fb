"""P4 — one identification, 14 angles, N = 5000 samples, to convergence (performance.md).

Data: the off-line simulator's ground-test aircraft with the six static conditions held 4 s
each (the variant ``loads.hold_s = 4, duration_s = 24``), so that one 5000-sample window
(25 s at 200 samples/s) holds every condition and informs every angle; the known-load
channels (load cells, inertial loads, reference balance) through the service's ``static``
content filter, the window taken after the filter has settled. Start: 4° on every angle
(true angles drawn within ±4°), no prior.

* ours — ``estimator.identification.KnownLoadProblem`` + ``levenberg_marquardt``
  (effective-variance likelihood, analytic sensitivities; time includes building the
  problem from the window);
* statsmodels — an ``MLEModel`` of the same 14 parameters on the same window, written as a
  user would: observation ``y = z − R₀ H`` with time-varying intercept ``S(θ) T`` and
  observation covariance ``W(θ)`` (the same W as ours), a dummy state; ``fit()`` with its
  defaults (L-BFGS, numerical gradients). Its Gaussian likelihood includes ``log det W(θ)``,
  which model.md §7 leaves out on purpose, so the two estimates differ by about one σ —
  both are scored against the truth in the result line.

Targets: ≤ 1 s and ≥ 10× statsmodels; ≤ 6 iterations from the 4° start.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from bench.common import arg_parser, interleaved, ratio, writer_from_args
from rsra.config.rig import RigConfig, load_config
from rsra.estimator.balance import inertial_loads, measurement_covariance
from rsra.estimator.content import ContentFilter
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.identification import KnownLoadProblem, Parameterisation, levenberg_marquardt
from rsra.estimator.params import RigModel
from rsra.sim_bus import load_scenario, simulate

BENCH = "p4_identification"
START_DEG = 4.0
HOLD_S = 4.0


def known_load_window(cfg: RigConfig, n: int, seed: int, hold_s: float = HOLD_S):
    """(z, T, H, alpha_true) of an n-sample window of content-filtered known-load data."""
    model = cfg.rig_model()
    base = load_scenario("ground-test")
    n_cond = len(base.loads.conditions)
    sc = load_scenario("ground-test", **{"loads.hold_s": hold_s, "duration_s": hold_s * n_cond})
    cf = ContentFilter(cfg.identification.content_known_loads, cfg.sample_rate_hz,
                       cfg.rotor.omega_nominal_rad_s, tuple(cfg.filter.harmonics), 7 + 6 + 6)
    run = simulate(cfg, sc, seed=seed, n_samples=n + cf.settle_samples)
    z = inertial_loads(model, run.accel)
    Y = cf.process(np.hstack([run.T, z, run.H_balance]))[cf.settle_samples:]
    return Y[:, 7:13], Y[:, :7], Y[:, 13:], run.alpha_true[0], cf.settle_samples


def statsmodels_model(model: RigModel, moment_floor: float, z: np.ndarray, T: np.ndarray,
                      H: np.ndarray, start: np.ndarray):
    """The statsmodels MLEModel a user would write for the known-load problem."""
    from statsmodels.tsa.statespace.mlemodel import MLEModel

    R0 = hub_transfer_matrix(model.geometry, "body")
    names = list(model.geometry.angle_names)

    class KnownLoadMLE(MLEModel):
        def __init__(self) -> None:
            super().__init__(z - H @ R0.T, k_states=1, initialization="known",
                             initial_state=[0.0], initial_state_cov=[[0.0]])
            self["design"] = np.zeros((6, 1))
            self["transition"] = np.eye(1)
            self["selection"] = np.eye(1)
            self["state_cov"] = np.zeros((1, 1))

        @property
        def param_names(self) -> list[str]:
            return names

        @property
        def start_params(self) -> np.ndarray:
            return start

        def update(self, params, **kw):
            params = super().update(params, **kw)
            self["obs_intercept"] = wrench_matrix(model.geometry, params) @ T.T
            self["obs_cov"] = measurement_covariance(model, params, moment_floor,
                                                     known_loads=True)
            return params

    return KnownLoadMLE()


def chi2_of(err: np.ndarray, P: np.ndarray) -> float:
    return float(err @ np.linalg.solve(P, err))


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
    model = cfg.rig_model()
    floor = cfg.identification.moment_floor_Nm
    n, rounds, sm_maxiter = (600, 1, 3) if args.tiny else (5000, 5, 1000)
    z, T, H, a_true, settle = known_load_window(cfg, n, seed=3)
    start = np.full(14, np.deg2rad(START_DEG))
    out: dict = {}

    def ours() -> float:
        t0 = time.perf_counter()
        par = Parameterisation(model, None, None, moment_floor=floor, known_loads=True)
        res = levenberg_marquardt(KnownLoadProblem(par, z, T, H), start, None,
                                  max_iterations=cfg.identification.max_iterations)
        dt = time.perf_counter() - t0
        out["ours"] = res
        return dt

    def peer() -> float:
        t0 = time.perf_counter()
        m = statsmodels_model(model, floor, z, T, H, start)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # convergence chatter of the optimiser
            r = m.fit(start_params=start, disp=False, maxiter=sm_maxiter,
                      approx_complex_step=False)
        dt = time.perf_counter() - t0
        out["statsmodels"] = r
        return dt

    res_o = interleaved({"ours": ours}, rounds)["ours"]
    res_p = interleaved({"statsmodels": peer}, 1)["statsmodels"]
    t_ours, t_sm = min(res_o), min(res_p)
    r_ours, r_sm = out["ours"], out["statsmodels"]
    chi2_ours = chi2_of(r_ours.theta - a_true, r_ours.P)
    chi2_sm = chi2_of(np.asarray(r_sm.params) - a_true, r_ours.P)
    rv = ratio(t_sm, t_ours)
    common = {
        "samples": n, "parameters": 14, "start_deg": START_DEG, "seed": 3, "content": cfg.identification.content_known_loads, "content_settle_samples": settle,
        "rounds_ours": rounds, "all_rounds_s": {"ours": res_o, "statsmodels": res_p},
        "ours_iterations": r_ours.iterations, "ours_status": r_ours.status,
        "ours_sigma_cr_deg_max": float(np.rad2deg(r_ours.sigma_cr).max()),
        "ours_chi2_vs_truth": chi2_ours,
        "statsmodels_iterations": r_sm.mle_retvals.get("iterations"),
        "statsmodels_function_calls": r_sm.mle_retvals.get("fcalls"),
        "statsmodels_converged": r_sm.mle_retvals.get("converged"),
        "statsmodels_chi2_vs_truth_with_our_P": chi2_sm,
        "max_difference_statsmodels_vs_ours_in_sigma": float(np.max(np.abs(
            (np.asarray(r_sm.params) - r_ours.theta) / r_ours.sigma_cr))),
        "chi2_14_single_run_limit": 36.1,
        "note": "statsmodels maximises the Gaussian likelihood with log det W(θ); ours leaves it "
             "out (model.md §7)"}
    w.add("time_vs_statsmodels", t_ours, "s", peer="statsmodels MLEModel.fit (L-BFGS, "
          "numerical gradients)", peer_figure=t_sm, ratio_value=rv, ratio_is="peer/figure",
          target="≤ 1 s and ≥ 10 × statsmodels",
          met=t_ours <= 1.0 and rv is not None and rv >= 10.0, **common)
    w.add("iterations_from_4deg", float(r_ours.iterations), "iterations", target=
          "≤ 6 iterations from a 4° start (informative data), converged",
          met=r_ours.iterations <= 6 and r_ours.status == "converged", **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
