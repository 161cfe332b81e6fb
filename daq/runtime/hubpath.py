"""The compiled hub path (docs/performance.md "The compiled hub path").

For a measured sample — every reading present and finite, no status, stuck, lost or
missing flag, no structure correction, a rotor speed the filter has its design for — the
estimator's first step (inertial loads, static estimate, load filter, transient test, the
angles' share of the variance, the filtered loads' own error σ ``sigma_filter`` —
estimator/filter_sigma.py, for a design whose error gain is diagonal, the report's) are
computed by one call of the C kernel ``rsra.daq._hubkernel`` instead of ≈ 45 numpy calls. Every other sample
takes the pure-Python reference path (``EstimatorPipeline.stages``), which stays what the
kernel is tested against: both give the same records bit for bit (tests/test_hubpath.py),
because the kernel's matrix products are numpy's own BLAS functions, called as numpy's
``ndarray.dot`` calls them, and its elementwise steps are the same IEEE operations.

The matrices are the pipeline's own arrays (the load filter's fused matrix and state, the
transient detector's, the balance's), held by the kernel's plan without copying; a plan is
rebuilt when any of them is replaced (a redesign, new angles).

:func:`load` finds the kernel and numpy's BLAS once: numpy's ``cblas_dgemv``/``cblas_ddot``
in the library numpy itself loaded, checked bit for bit against ``ndarray.dot`` on the
shapes the kernel uses. Anything missing — the extension not built (no compiler at install),
a numpy whose BLAS cannot be found or gives other bits — leaves the kernel off with the
reason, which the service logs and reports in ``health`` (``estimator.hub_kernel``).
"""
from __future__ import annotations

import ctypes
import logging
import math
import os
from typing import Any

import numpy as np

log = logging.getLogger("rsra.pipeline")
_STATE: dict[str, Any] = {}
OFF_ENV = "RSRA_HUB_KERNEL"  # "off": the pure-Python path (benchmarks' before/after)


# The estimator code the kernel mirrors (daq/_hubkernel.c does what these do, in their
# order): a change to any of them turns the kernel off with the reason until the kernel is
# brought in line and tests/test_hubpath.py shows both paths equal again (then put the new
# fingerprint here: ``python -c "from rsra.daq.runtime import hubpath; print(hubpath.
# estimator_fingerprint())"``).
MIRRORS_FINGERPRINT = "fe119818fa35fe3e"  # design mode; azimuth mode takes the reference path


def _code_only(source: str) -> str:
    """The code of a function's source: its syntax tree without type annotations, docstrings
    or comments, so that annotating the estimator for mypy does not turn the kernel
    off, while any change to what the code computes does."""
    import ast
    import textwrap

    class Strip(ast.NodeTransformer):
        def visit_arg(self, node: ast.arg) -> ast.arg:
            node.annotation = None
            return node

        def visit_FunctionDef(self, node: ast.FunctionDef) -> ast.FunctionDef:
            node.returns = None
            body = node.body
            if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                node.body = body[1:] or [ast.Pass()]
            self.generic_visit(node)
            return node

        def visit_AnnAssign(self, node: ast.AnnAssign) -> ast.AST | None:
            if node.value is None:  # a declaration only
                return None
            return ast.Assign(targets=[node.target], value=self.visit(node.value))

    tree = Strip().visit(ast.parse(textwrap.dedent(source)))
    return ast.dump(tree)


def estimator_fingerprint() -> str:
    """A hash of the code (:func:`_code_only`) of the estimator steps the kernel mirrors."""
    import hashlib
    import inspect

    from rsra.estimator.angle_uncertainty import HubAngleVariance
    from rsra.estimator.content import ContentFilter
    from rsra.estimator.filter_sigma import FilterSigma
    from rsra.estimator.filters import LoadFilter
    from rsra.estimator.transient import TransientDetector

    h = hashlib.sha256()
    for f in (LoadFilter._build, LoadFilter.step, LoadFilter._measured, LoadFilter._predicted,
              TransientDetector.update,
              HubAngleVariance.variance, HubAngleVariance.__init__, ContentFilter._step,
              ContentFilter.process, FilterSigma.update):
        try:
            h.update(_code_only(inspect.getsource(f)).encode())
        except (OSError, TypeError):  # no source (a frozen install): cannot tell
            return "unknown"
    return h.hexdigest()[:16]


def _numpy_blas_paths() -> list[str]:
    """The shared libraries numpy loaded that may be its BLAS (numpy's own first)."""
    base = os.path.dirname(os.path.dirname(np.__file__))
    found: list[str] = []
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            for line in f:
                parts = line.split(None, 5)
                if len(parts) == 6:
                    p = parts[5].strip()
                    if "blas" in os.path.basename(p).lower() and p not in found:
                        found.append(p)
    except OSError:
        return []
    # numpy's own (numpy.libs/ of a wheel) before any other BLAS in the process (scipy's)
    return sorted(found, key=lambda p: ("numpy" not in p.lower(), not p.startswith(base)))


def _find_blas() -> tuple[int, int, bool, str] | str:
    """(dgemv address, ddot address, ILP64, where) of numpy's CBLAS, or why not."""
    conf: Any = {}
    try:
        conf = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    except Exception:  # noqa: BLE001 - any numpy without the config
        pass
    ilp64_conf = "USE64BITINT" in str(conf.get("openblas configuration", ""))
    for path in _numpy_blas_paths():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix, ilp64 in (("scipy_", "64_", True), ("", "64_", True),
                                      ("scipy_", "", False), ("", "", ilp64_conf)):
            try:
                g = getattr(lib, f"{prefix}cblas_dgemv{suffix}")
                d = getattr(lib, f"{prefix}cblas_ddot{suffix}")
            except AttributeError:
                continue
            ga, da = ctypes.cast(g, ctypes.c_void_p).value, ctypes.cast(d, ctypes.c_void_p).value
            if ga is None or da is None:  # (a found symbol's address is never NULL)
                continue
            return ga, da, ilp64, f"{os.path.basename(path)}:{prefix}cblas_dgemv{suffix}"
    return "numpy's CBLAS (cblas_dgemv, cblas_ddot) not found among the loaded libraries"


def _self_check(k: Any) -> str | None:
    """The kernel's gemv and numpy's dot, bit for bit, on the shapes of the hub path, with
    C- and Fortran-ordered matrices (numpy passes them to BLAS differently)."""
    rng = np.random.default_rng(26)
    for m, n in ((6, 6), (6, 7), (6, 9), (42, 7), (48, 43), (60, 55), (6, 3), (66, 61)):
        for i in range(20):
            A = rng.standard_normal((m, n)) * 10.0 ** rng.integers(-3, 4)
            x = rng.standard_normal(n) * 10.0 ** rng.integers(-3, 4)
            y = np.empty(m)
            fortran = i % 2 == 1
            if fortran:
                A = np.asfortranarray(A)
                k.gemv(A.T, m, n, True, x, y)  # (A.T: the same memory, C-ordered)
            else:
                k.gemv(A, m, n, False, x, y)
            if y.tobytes() != A.dot(x).tobytes():
                return (f"the kernel's BLAS gives other bits than numpy's dot ({m}×{n}, "
                        f"{'Fortran' if fortran else 'C'} order)")
    return None


def load() -> tuple[Any, str]:
    """(the kernel module or None, a one-line description: where its BLAS is, or why not)."""
    if "kernel" in _STATE:
        return _STATE["kernel"], _STATE["why"]
    kernel, why = None, ""
    if os.environ.get(OFF_ENV, "").lower() == "off":
        why = f"off ({OFF_ENV}=off)"
    else:
        try:
            from rsra.daq import _hubkernel as k
        except ImportError as e:
            why = f"not built ({e}); reinstall with a C compiler (pip install .)"
        else:
            blas = _find_blas()
            fp = estimator_fingerprint()
            if fp != MIRRORS_FINGERPRINT:
                why = (f"off: the estimator steps it mirrors changed (fingerprint {fp}, "
                       f"the kernel follows {MIRRORS_FINGERPRINT}; daq/runtime/hubpath.py)")
            elif isinstance(blas, str):
                why = blas
            else:
                k.set_blas(blas[0], blas[1], blas[2])
                bad = _self_check(k)
                if bad:
                    why = bad
                else:
                    kernel, why = k, f"compiled ({blas[3]})"
    _STATE["kernel"], _STATE["why"] = kernel, why
    return kernel, why


class HubKernel:
    """The kernel's side of one pipeline: its plan (rebuilt when an array it holds is
    replaced) and the fast first step (:meth:`first_step`: None where the reference path
    must run)."""

    def __init__(self, kernel: Any, pipeline: Any):
        self.k = kernel
        self.p = pipeline
        self._plan = None
        self._held: tuple = ()
        self.samples = 0  # samples the kernel computed
        self.sigma_samples = 0  # … and their sigma_filter (a diagonal error gain) too
        # the kernel can write the record's JSON text too (float.__repr__'s digits through
        # PyOS_double_to_string), but that costs ≈ 1 µs a double where orjson's encoder
        # (rsra.daq.jsonout.dumpb) takes ≈ 0.2: off, measured (docs/performance.md)
        self._frame_json = ('"' + pipeline.frame + '"').encode()
        if not pipeline.frame.isascii() or any(c in pipeline.frame for c in '"\\'):
            raise ValueError("the hub frame's name needs escaping")

    def _plan_for(self, lf, tr, av, fs, c) -> Any:
        p = self.p
        angles = p.angles
        h = self._held
        if h and (h[0] is lf._G and h[1] is lf._buf and h[2] is p._Mf and h[3] is p._Rinv
                  and h[4] is angles.S and h[5] is tr._Mb and h[6] is tr._s and h[7] is av._Q2
                  and h[8] is p._D and h[9] is angles.bound2 and h[10] is c
                  and h[11] is fs._Mf and h[12] is fs._Ms and h[13] is fs.floor):
            return self._plan
        held = (lf._G, lf._buf, p._Mf, p._Rinv, angles.S, tr._Mb, tr._s, av._Q2, p._D,
                angles.bound2, c, fs._Mf, fs._Ms, fs.floor)
        self._plan = None
        self._held = held
        D = p._D if p._D.shape[1] else None
        # FilterSigma's step (the diagonal error gain of the report's tuning; another gain's
        # einsum stays in Python): its design constants and its averages, held as the rest
        sig = ({"fs_Rinv": c.Rinv, "fs_Bu": c.B_u, "fs_modelled": c.modelled, "fs_g2": c.g2,
                "fs_Mf": fs._Mf, "fs_Ms": fs._Ms, "fs_floor": fs.floor,
                "beta_fast": fs.beta_fast, "beta_slow": fs.beta_slow} if c.diag else {})
        self._plan = self.k.Plan(p._Mf, p._Rinv, angles.S, lf._G, lf._buf, tr._Mb, tr._s,
                                 av._Q2, D, angles.bound2, lf._n, 1.0 - tr.beta, tr.threshold,
                                 self._frame_json, **sig)
        return self._plan

    def first_step(self, s, seq: int, T: np.ndarray, accel: np.ndarray, q) -> tuple | None:
        """A measured sample's first step, or None (nothing changed: the reference runs).
        Returns (I, z, e, nis, omega, hub_loads record)."""
        p = self.p
        omega = s.omega if s.omega is not None and math.isfinite(s.omega) else None
        if omega is not None and not p.omega_low <= omega < p.omega_max:
            return None  # refused: the reference counts and flags it
        if p._last_seq is not None and seq - p._last_seq - 1 > 0:
            return None  # a gap to predict through
        lf, tr, av, fs = p.load_filter, p.transient, p.angles.var, p.filter_sigma
        try:
            lf.set_omega(omega)
        except (ValueError, np.linalg.LinAlgError):
            return None  # the reference counts the failure and keeps the design
        if tr._design is not lf._design:
            return None  # the detector converts its state to a new design (reference)
        c = fs._for(lf.design)  # (FilterSigma.update's own lookup of the design's constants)
        try:
            plan = self._plan_for(lf, tr, av, fs, c)
        except (ValueError, BufferError) as e:  # an array the kernel cannot take as numpy does
            p.hub_kernel = None
            p.hub_kernel_status = f"off ({type(e).__name__}: {e})"
            log.warning("compiled hub path off: %s; the pure-Python path runs", e)
            return None
        n = lf._n
        out = np.empty(42 + n)
        flags = list(lf._flags)
        tail = ("identification_off",) if p.identification_off else ()
        omega_pub = omega if omega is not None else (
            None if p.cfg.rotor.stopped else p.cfg.rotor.omega_nominal_rad_s)
        t = float(s.t)
        sync = int(s.sync)
        # FilterSigma.update's per-sample step in the kernel (bit 0), with its two flags:
        # its averages started (bit 1), the slow one past its settling (bit 2)
        fs_mode = (1 | (2 if fs._started else 0) | (4 if fs._n >= fs.settle else 0)
                   if c.diag else 0)
        text, nis, tq, _transient, uncertain = plan.step(T, accel, q, out, seq, sync, t,
                                                         omega_pub, flags, tail, False, fs_mode)
        p._last_seq = seq
        lf._run = 0
        tr.q = tq
        sigma = out[24:30]
        p.angles.sigma = sigma  # (AnglesInForce.measure's results)
        p.angles.uncertain = uncertain
        if fs_mode:  # the rest of FilterSigma.update: its counters and its result
            fs._started = True
            fs._n += 1
            sigma_filter = fs.sigma = out[36 + n:]
            self.sigma_samples += 1
        else:  # another error gain: the reference's own call on the same innovation
            sigma_filter = fs.update(lf.design, out[18:24])
        rec = {"seq": seq, "sync": sync, "t": t, "frame": p.frame, "H": out[12:18],
               "H_static": out[6:12], "sigma_angles": sigma, "sigma_filter": sigma_filter,
               "omega": omega_pub, "flags": flags}
        self.samples += 1
        return out[0:6], out[30:36], out[18:24], nis, omega, rec

    def content_step(self, cf, x: np.ndarray) -> np.ndarray:
        """One sample ``x`` through the content filter ``cf`` (estimator.content
        .ContentFilter: ``cf.process(x[None, :])[0]``, the same values): its sections run in
        the kernel on its own state; the first sample (the state is set up from it), an
        identity filter or arrays the kernel cannot take go through ``cf.process``."""
        zi = cf._zi
        if (zi is None or cf._identity or x.dtype != np.float64 or not x.flags.c_contiguous
                or not zi.flags.c_contiguous or not cf.sos.flags.c_contiguous
                or cf.sos.dtype != np.float64):
            return cf.process(x[None, :])[0]
        y = np.empty(x.shape[0])
        self.k.sos_step(cf.sos, zi, x, y)
        return y
