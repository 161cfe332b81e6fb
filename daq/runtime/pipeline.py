"""The estimator thread's per-sample work (docs/architecture.md, the data flow), free of I/O:

sample → stuck-channel test → inertial loads → static estimate → load filter → records;
        └→ calibration branch: content filter → window buffer → identification jobs.

Identification results are applied from a stated sample (`applies_from_seq`), so a replay
that feeds the recorded `angles` records through `deliver()` reproduces a live run exactly.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rsra.config.rig import ConfigError, RigConfig
from rsra.config.rigfile import DESIGN_BAND
from rsra.daq.bus.assembler import channels_payload
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.rigmodel import design_cache
from rsra.daq.runtime.angles_in_force import AnglesInForce
from rsra.daq.runtime.calibration_branch import CalibrationBranch
from rsra.daq.runtime.hubpath import HubKernel
from rsra.daq.runtime.hubpath import load as load_hub_kernel
from rsra.daq.runtime.records import AnglesRecord, IdentJob
from rsra.daq.runtime.result_schedule import ResultSchedule
from rsra.daq.runtime.stuck import StuckMonitor
from rsra.estimator.angle_uncertainty import ANGLES_UNCERTAIN
from rsra.estimator.balance import inertial_load_matrix, measurement_covariance
from rsra.estimator.filter_sigma import FilterSigma, ReferenceSigma
from rsra.estimator.filters import AZIMUTH_MISSING, AzimuthTracker, DesignCache, LoadFilter
from rsra.estimator.geometry import hub_transfer_matrix
from rsra.estimator.noise_budget import noise_budget
from rsra.estimator.structure import StructureCorrection
from rsra.estimator.transient import TIME_CONSTANT_FRACTION, TRANSIENT, TransientDetector

log = logging.getLogger("rsra.pipeline")

PREFILL_BAND = DESIGN_BAND  # the rotor-speed band designed at start-up (flight: +-2 %)
IMPLAUSIBLE_OMEGA = "implausible:omega"  # the flag of a rotor-speed reading refused


@dataclass
class PipelineOutput:
    # (kind, payload): a dict, or a typed record (the applied angles: records.AnglesRecord)
    records: list[tuple[str, dict[str, Any] | AnglesRecord]] = field(default_factory=list)
    job: IdentJob | None = None  # an identification window to submit


class EstimatorPipeline:
    """Per-sample estimation for the live service and for replay (one code path): each
    sample's first step (:meth:`stages`: inertial loads, static estimate, load filter, the
    hub_loads record) and its second (channels, innovations, the calibration branch), over
    the pieces with a job of their own — the schedule of identification results
    (``results``: result_schedule.ResultSchedule), the angles in force (``angles``:
    angles_in_force.AnglesInForce) and the calibration branch (``calibration``:
    calibration_branch.CalibrationBranch)."""

    def __init__(self, cfg: RigConfig, alpha0: np.ndarray, *, identification: bool = True,
                 table: DecodeTable | None = None, hub_kernel: bool = True,
                 prefill: bool = True):
        self.cfg = cfg
        self.model = cfg.rig_model()
        self.fs = cfg.sample_rate_hz
        self.frame = cfg.hub_frame
        alpha = np.asarray(alpha0, float).copy()
        self._Rinv = np.linalg.inv(hub_transfer_matrix(self.model.geometry))
        self._Mf = inertial_load_matrix(self.model)
        self._D = self.model.external.wrenches
        f = cfg.filter
        # azimuth mode: the harmonic states turn with the rotor's measured azimuth
        self.azimuth_mode = cfg.rotor.harmonic_phase == "azimuth"
        self.azimuth = AzimuthTracker(cfg.rotor.omega_nominal_rad_s, 1.0 / self.fs)
        self.azimuth_missing = 0  # samples advanced by the design's Ω (health)
        self.cache = design_cache(cfg, model=self.model)
        self.load_filter = _load_filter(cfg, self.cache, alpha, self.azimuth_mode, prefill)
        # the filter's lag behind a moving static load: flag `transient` (estimator/transient.py)
        self.transient = TransientDetector(1.0 / self.fs,
                                           TIME_CONSTANT_FRACTION * f.time_constant_s)
        # the filter's own error σ (`sigma_filter`): the sensors' noise through the gain for a
        # held load plus what the innovations show it does not follow, no smaller than the
        # error a reference balance on the bus shows (estimator/filter_sigma.py)
        # (the sensors' noise as the config states it: W without the identification's
        # model-error floor on the moment rows, which is no noise the sensors make)
        self.filter_sigma = FilterSigma(
            1.0 / self.fs, f.time_constant_s,
            noise=measurement_covariance(self.model, cfg.identification.initial_angles_rad,
                                         moment_floor=0.0))
        # the reference reads body axes at the hub: into the hub loads' frame
        to_hub = self._Rinv @ hub_transfer_matrix(self.model.geometry, "body")
        self._to_hub = None if np.allclose(to_hub, np.eye(6), rtol=0, atol=1e-12) else to_hub
        self.reference_sigma = ReferenceSigma(
            1.0 / self.fs, f.time_constant_s,
            np.einsum("ij,j,ij->i", to_hub, np.asarray(self.model.balance_sigma) ** 2, to_hub))
        self.cell_names = [c.name for c in cfg.cells]
        self.innov_every = max(1, int(round(self.fs / cfg.telemetry.innovations_hz)))
        idc = cfg.identification
        self.identification = identification
        self.identification_off = False  # the worker died too often (service): hub_loads say so
        self.results = ResultSchedule()
        self.calibration = CalibrationBranch(cfg, self.results)
        self.first_seq: int | None = None
        # a rotor speed whose highest modelled harmonic is at or above Nyquist cannot be
        # designed for (and no rotor gives one): such a reading is not used (model §5)
        self.omega_max = math.pi * self.fs / max(cfg.filter.harmonics)
        # a rotor turns one way: a reading below minus the stopped band (a stopped rotor's
        # noise) is a sign-inverted or corrupt sensor, not a stopped rotor
        self.omega_low = -cfg.rotor.omega_min_fraction * cfg.rotor.omega_nominal_rad_s
        self.implausible_omega = 0  # readings refused (counted in health)
        self._last_seq: int | None = None
        self.design_errors = 0  # redesigns that failed: the current design was kept
        # stuck channels (a frozen sensor with a clean status, daq/runtime/stuck.py): flagged
        # fault:<cell|accelerometer> and treated like a faulted cell — predict-only (model
        # §6), H_static null, not ok in the identification window
        self.stuck = StuckMonitor(cfg, table) if cfg.stuck.enabled else None
        # the angles in force and how far they can move the hub loads (`sigma_angles`, flag
        # `angles_uncertain` above the static noise bound: `rsra noise-budget`, model §4)
        self.angles = AnglesInForce(
            self.model, alpha, idc.prior_sigma_rad,
            noise_budget(self.model, idc.initial_angles_rad).total ** 2, self.load_filter)
        # the compiled hub path (daq/runtime/hubpath.py): measured samples' first step in one
        # call, the same records bit for bit; None: the reference path only (the status: why)
        self.hub_kernel, self.hub_kernel_status = _hub_kernel(self, hub_kernel)

    # --- the pieces' faces (the service, start-up, tests) ------------------------------
    @property
    def alpha(self) -> np.ndarray:
        """The identified angles in force (AnglesInForce.alpha)."""
        return self.angles.alpha

    @property
    def structure(self) -> StructureCorrection | None:
        """A selected structure in force, or None (AnglesInForce.structure)."""
        return self.angles.structure

    @property
    def outstanding(self) -> dict[int, int]:
        """The jobs awaited: job id -> planned apply sample (ResultSchedule.outstanding)."""
        return self.results.outstanding

    def deliver(self, rec: AnglesRecord, arrival_seq: int | None = None,
                job_id: int | None = None) -> None:
        """Hand over an identification result (ResultSchedule.deliver); any thread."""
        self.results.deliver(rec, arrival_seq, job_id)

    def waiting_for(self, seq: int) -> list[int]:
        """Jobs whose result must be in before sample `seq` is processed (lock-step)."""
        return self.results.waiting_for(seq)

    def final_records(self, after_seq: int) -> list[AnglesRecord]:
        """At the end of a run: the results no sample applied (ResultSchedule.final_records)."""
        return self.results.final_records(after_seq)

    def _apply_due(self, seq: int, out: PipelineOutput) -> None:
        """The identification results due at sample ``seq``, into force and published."""
        if self.results.due_now(seq):
            for rec in self.results.due(seq):
                self.angles.apply(rec)
                out.records.append(("angles", rec))

    # --- the per-sample path ----------------------------------------------------------
    def first_step_is_quick(self, s) -> bool:
        """The first step of sample ``s`` takes no slow work: no identification result to
        take in or apply (new angles redesign the filter: ms), no filter design for its rotor
        speed (a cache miss: 10–60 ms). Live, only such a step runs in the bus thread."""
        if self.results.due_now(int(s.seq)):
            return False
        omega = s.omega
        if omega is not None and not (math.isfinite(omega)
                                      and self.omega_low <= omega < self.omega_max):
            return True  # refused or missing: no redesign for it (stages)
        return self.cache.has_design(omega, current=self.load_filter.design)

    def process(self, s) -> PipelineOutput:
        """One sample: every record and the identification job, if one is due."""
        first, rest = self.stages(s)
        first.records.extend(rest.records)
        first.job = rest.job
        return first

    def stages(self, s) -> Iterator[PipelineOutput]:
        """One sample in two steps the caller pulls (live): first the records up to and
        including hub_loads, then the channels, innovations and calibration branch — off the
        SYNC → hub-load latency path. Both steps must be taken, in
        order; live, the first runs in the bus thread and the second in the service thread
        (the first step of the next sample may run while this one's second runs: what the
        second needs of the first is passed in the generator's locals, never in ``self``)."""
        out = PipelineOutput()
        seq = int(s.seq)
        if self.first_seq is None:
            self.first_seq = seq
        self._apply_due(seq, out)
        alpha = self.angles.alpha  # the angles in force for this sample (set_alpha replaces it)
        T = np.asarray(s.T, float)
        accel = np.asarray(s.accel, float).reshape(-1)
        flags = list(s.flags)
        stuck = False
        present = False  # every cell and accelerometer reading finite, known already
        if self.stuck is not None:
            for fl in self.stuck.update(T, accel, s.flags):
                stuck = True
                if fl not in flags:
                    flags.append(fl)
            present = self.stuck.detector.fresh
        if present:
            cells_ok = acc_ok = True
        else:
            # (np.count_nonzero: a fraction of ndarray.all's cost on these short vectors)
            cells_ok = np.count_nonzero(np.isfinite(T)) == T.size
            acc_ok = np.count_nonzero(np.isfinite(accel)) == accel.size
        bad_status = stuck or (bool(flags) and
                               any(f.startswith(("overrange:", "fault:")) for f in flags))
        q = None
        drive_ok = True
        if self._D.shape[1]:
            q = None if s.drive is None else np.asarray(s.drive, float)
            drive_ok = q is not None and np.count_nonzero(np.isfinite(q)) == q.size
        measured = cells_ok and acc_ok and drive_ok and not bad_status
        fast = None
        dpsi = None
        if (measured and not flags and self.hub_kernel is not None
                and self.angles.structure is None):
            # the compiled hub path (daq/runtime/hubpath.py): the same records bit for bit;
            # None where this sample needs the reference path below
            fast = self.hub_kernel.first_step(s, seq, T, accel, q)
        if fast is not None:
            I, z, e, nis, omega, rec = fast
            out.records.append(("hub_loads", rec))
        else:
            I, z, e, nis, omega, dpsi = self._first_reference(s, seq, T, accel, q, flags,
                                                              measured, acc_ok, drive_ok, out)
        kind, hub = out.records[-1]
        if kind == "hub_loads" and isinstance(hub, dict):
            self._reference_sigma(s, hub)
        yield out
        out = PipelineOutput()
        status = s.cell_status
        if not isinstance(status, dict):
            status = {n: int(b) for n, b in zip(self.cell_names, status)}
        out.records.append(("channels", channels_payload(s, I=I, status=status)))
        if (seq - self.first_seq) % self.innov_every == 0:
            out.records.append(("innovations", {"seq": seq, "t": float(s.t), "e": e,
                                                "nis": nis}))
        if self.identification:
            out.job = self.calibration.step(s, seq, seq - self.first_seq + 1, T, z, measured,
                                            omega, alpha, dpsi, flags, self.hub_kernel)
        yield out

    def _reference_sigma(self, s, hub: dict) -> None:
        """A reference balance's reading on this sample: sigma_filter no smaller than the
        error of H it shows (estimator/filter_sigma.ReferenceSigma; either path's record)."""
        known = getattr(s, "known_H", None)
        if known is None or hub["H"] is None:
            return
        known = np.asarray(known, float)
        if known.shape != (6,):
            return
        ref = self.reference_sigma
        ref.update(hub["H"] - (known if self._to_hub is None else self._to_hub @ known))
        hub["sigma_filter"] = ref.widen(hub["sigma_filter"])

    def _first_reference(self, s, seq, T, accel, q, flags, measured, acc_ok, drive_ok,
                         out) -> tuple:
        """The first step's reference path (numpy): every sample the compiled hub path does
        not take, and all of them without it. Returns (I, z, e, nis, omega, dpsi)."""
        I, z, zh, H_static = self._static_hub_load(T, accel, q, measured, acc_ok, drive_ok)
        omega, refused = self._take_omega(s.omega, flags)
        lost = self._lost_before(s, seq)
        dpsi = (self.azimuth.step(s.azimuth, omega, lost + 1) if self.azimuth_mode else None)
        res = self.load_filter.step(T if measured else np.zeros(7), zh if measured else np.zeros(6),
                                    measured=measured, lost=lost, dpsi=dpsi)
        sigma_filter = self._after_filter(res, dpsi, flags)
        if measured:  # (predict-only: H comes from earlier samples, and so does their σ)
            self.angles.measure(T)
        sigma_angles = None if res.H is None else self.angles.sigma
        if sigma_angles is not None and self.angles.uncertain:
            flags.append(ANGLES_UNCERTAIN)
        omega_pub = omega if omega is not None else (
            None if self.cfg.rotor.stopped or refused else self.cfg.rotor.omega_nominal_rad_s)
        out.records.append(("hub_loads", {
            "seq": seq, "sync": int(s.sync), "t": float(s.t), "frame": self.frame,
            "H": None if res.H is None else res.H, "H_static": H_static,
            "sigma_angles": sigma_angles,
            "sigma_filter": None if res.H is None else sigma_filter,
            "omega": omega_pub, "flags": flags}))
        return I, z, res.e, res.nis, omega, dpsi

    def _static_hub_load(self, T, accel, q, measured, acc_ok, drive_ok) -> tuple:
        """(I, z, z as the structure corrects it, the static hub load or None)."""
        # (ndarray.dot: the same BLAS gemv as @, at half the call cost on these sizes)
        I = self._Mf.dot(accel) if acc_ok else np.full(6, np.nan)
        z = I - self._D.dot(q) if (q is not None and drive_ok) else I
        if not measured:
            return I, z, z, None
        angles = self.angles
        zh = z if angles.structure is None else angles.structure.correct(z, T)
        return I, z, zh, self._Rinv.dot(zh - angles.S.dot(T))

    def _take_omega(self, omega, flags: list[str]) -> tuple[float | None, bool]:
        """The sample's rotor speed for the filter (None: none), and whether it was refused
        as implausible; a plausible one redesigns the filter when it must."""
        omega = omega if omega is not None and math.isfinite(omega) else None
        if omega is not None and not self.omega_low <= omega < self.omega_max:
            # a corrupt or impossible reading (e.g. 1e12 rad/s, or -19.4 rad/s from a
            # sign-inverted sensor): no redesign for it — the design would fail or take the
            # estimator thread for tens of ms, or say the rotor stopped — and no value
            self.implausible_omega += 1
            for flag in (f"missing:{self.cfg.rotor.node}", IMPLAUSIBLE_OMEGA):
                if flag not in flags:
                    flags.append(flag)
            return None, True
        try:
            self.load_filter.set_omega(omega)
        except (ValueError, np.linalg.LinAlgError) as e:  # keep the current design
            self.design_errors += 1
            if self.design_errors == 1:
                log.error("filter redesign at omega=%r failed (%s); the current design "
                          "is kept", omega, e)
        return omega, False

    def _lost_before(self, s, seq: int) -> int:
        """Samples lost before this one: SYNCs lost on the bus (lost_before), and samples
        that never reached this step (a whole sample dropped from a full queue live, counted
        in health; a replay's gap) — both keep their seq, so the gap says how far to predict
        (model §6: Φ^k)."""
        lost = int(s.lost_before)
        if self._last_seq is not None and seq - self._last_seq - 1 > lost:
            lost = seq - self._last_seq - 1
        self._last_seq = seq
        return lost

    def _after_filter(self, res, dpsi, flags: list[str]):
        """The filter step's flags, the transient test and σ of the filter's error."""
        for fl in res.flags:
            if fl not in flags:
                flags.append(fl)
        if self.azimuth_mode and dpsi is None and AZIMUTH_MISSING in res.flags:
            self.azimuth_missing += 1
        design = self.load_filter.design
        if res.e is not None and self.transient.update(design, res.e):
            flags.append(TRANSIENT)
        sigma_filter = self.filter_sigma.update(design, res.e)
        if self.identification_off:
            flags.append("identification_off")
        return sigma_filter


def _load_filter(cfg: RigConfig, cache: DesignCache, alpha: np.ndarray,
                 azimuth: bool, prefill: bool = True) -> LoadFilter:
    """The pipeline's load filter, the rotor-speed band it is expected in designed now (a
    redesign takes 10-60 ms, longer than a sample); a design that fails is a ConfigError.
    ``prefill=False`` (a run not paced by the wall clock: a replay, lock-step) designs only
    the nominal speed now and every other one when first met: a design is a function of
    its grid speed alone, so the records are the same, and a replay does not spend its
    start-up on the band's designs it never meets."""
    f = cfg.filter
    fs = cfg.sample_rate_hz
    w0 = cfg.rotor.omega_nominal_rad_s
    try:
        if prefill:
            cache.prefill(w0 * (1 - PREFILL_BAND), w0 * (1 + PREFILL_BAND))
        return LoadFilter(cache, alpha, invalid_after_samples=int(round(f.invalid_after_s * fs)),
                          azimuth=azimuth)
    except (np.linalg.LinAlgError, ValueError) as e:  # the config check (Nyquist) passed
        if isinstance(e, ConfigError):
            raise
        why = " ".join(f"{type(e).__name__}: {e}".split())
        raise ConfigError(
            "filter", f"harmonics {list(f.harmonics)}, time_constant_s {f.time_constant_s:g}",
            f"the load filter cannot be designed at rig.sample_rate_hz = {fs:g} and "
            f"rotor.omega_nominal_rad_s = {w0:g} ({why})",
            "use fewer or lower harmonics, a longer time_constant_s or a higher sample rate",
            cfg.source) from None


def _hub_kernel(p: EstimatorPipeline, asked: bool) -> tuple[HubKernel | None, str]:
    """The compiled hub path for pipeline ``p`` (when ``asked``), or None; and its status."""
    if not asked:
        return None, "off (not asked)"
    if p.azimuth_mode:  # the kernel's filter step is the design's Φ
        return None, "not used (rotor.harmonic_phase = azimuth)"
    k, status = load_hub_kernel()
    if k is None:
        return None, status
    try:
        return HubKernel(k, p), status
    except ValueError as e:
        return None, f"not used ({e})"
