"""The estimator thread's per-sample work (docs/architecture.md, the data flow), free of I/O:

sample → stuck-channel test → inertial loads → static estimate → load filter → records;
        └→ calibration branch: content filter → window buffer → identification jobs.

Identification results are applied from a stated sample (`applies_from_seq`), so a replay
that feeds the recorded `angles` records through `deliver()` reproduces a live run exactly.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from rsra.config.rig import DESIGN_BAND, ConfigError, RigConfig
from rsra.daq.bus.assembler import channels_payload
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.runtime.hubpath import HubKernel
from rsra.daq.runtime.hubpath import load as load_hub_kernel
from rsra.daq.runtime.reasons import input_labels
from rsra.daq.runtime.records import ABSENT, AnglesRecord, IdentJob
from rsra.daq.runtime.stuck import StuckMonitor
from rsra.estimator.balance import inertial_load_matrix
from rsra.estimator.content import ContentFilter, MissingHold
from rsra.daq.rigmodel import design_cache
from rsra.estimator.angle_uncertainty import (
    ANGLES_UNCERTAIN,
    HubAngleVariance,
    angle_covariance,
)
from rsra.estimator.filter_sigma import FilterSigma
from rsra.estimator.filters import AZIMUTH_MISSING, AzimuthTracker, LoadFilter
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.noise_budget import noise_budget
from rsra.estimator.structure import StructureCorrection
from rsra.estimator.transient import TIME_CONSTANT_FRACTION, TRANSIENT, TransientDetector

log = logging.getLogger("rsra.pipeline")

PREFILL_BAND = DESIGN_BAND  # the rotor-speed band designed at start-up (flight: +-2 %)


@dataclass
class PipelineOutput:
    records: list[tuple[str, dict]] = field(default_factory=list)
    job: IdentJob | None = None  # an identification window to submit


class WindowBuffer:
    """Ring buffer of the content-filtered calibration data (bounded: one window)."""

    def __init__(self, n: int, n_acc_cols: int):
        self.n = n
        self.T = np.zeros((n, 7))
        self.z = np.zeros((n, 6))
        self.H = np.zeros((n, 6))
        self.seq = np.zeros(n, dtype=np.int64)
        self.t = np.zeros(n)
        self.ok = np.zeros(n, dtype=bool)  # load cells and accelerometers present
        self.known = np.zeros(n, dtype=bool)  # balance present
        self.omega = np.zeros(n)
        self.dpsi = np.full(n, np.nan)  # the rotor's turn since the last sample (azimuth mode)
        # what each sample lacked (bits of EstimatorPipeline.input_labels): reported in a
        # rejected run's explanation (daq.runtime.reasons), never used to decide
        self.missing = np.zeros(n, dtype=np.uint64)
        # the raw (not content-filtered) cell loads and z: the window's mean static load, for
        # the filter-error load excursion (issue 25)
        self.T_raw = np.zeros((n, 7))
        self.z_raw = np.zeros((n, 6))
        self.count = 0

    def add(self, seq, t, T, z, H, ok, known, omega, dpsi=None, missing: int = 0,
            raw: tuple | None = None) -> None:
        i = self.count % self.n
        self.T[i], self.z[i], self.H[i] = T, z, H
        if raw is not None:
            self.T_raw[i], self.z_raw[i] = raw
        self.dpsi[i] = np.nan if dpsi is None else dpsi
        self.seq[i], self.t[i], self.ok[i], self.known[i], self.omega[i] = seq, t, ok, known, omega
        self.missing[i] = missing
        self.count += 1

    def window(self) -> dict:
        """The last n samples in time order (copies: the job leaves this thread)."""
        m = min(self.count, self.n)
        idx = (np.arange(self.count - m, self.count)) % self.n
        return {"T": self.T[idx].copy(), "z": self.z[idx].copy(), "known_H": self.H[idx].copy(),
                "seq": self.seq[idx].copy(), "t": self.t[idx].copy(), "ok": self.ok[idx].copy(),
                "known": self.known[idx].copy(), "omega": self.omega[idx].copy(),
                "dpsi": self.dpsi[idx].copy(),
                "missing": self.missing[idx].copy(),
                **self._raw_means(idx)}

    def _raw_means(self, idx: np.ndarray) -> dict:
        """The window's mean raw cell loads and z over its complete samples (None: none)."""
        ok = self.ok[idx]
        if not ok.any():
            return {"T_mean": None, "z_mean": None}
        return {"T_mean": self.T_raw[idx][ok].mean(axis=0),
                "z_mean": self.z_raw[idx][ok].mean(axis=0)}


class EstimatorPipeline:
    """Per-sample estimation for the live service and for replay (one code path)."""

    def __init__(self, cfg: RigConfig, alpha0: np.ndarray, *, identification: bool = True,
                 table: DecodeTable | None = None, hub_kernel: bool = True):
        self.cfg = cfg
        self.model = cfg.rig_model()
        self.fs = cfg.sample_rate_hz
        self.frame = cfg.hub_frame
        self.alpha = np.asarray(alpha0, float).copy()
        self.structure: StructureCorrection | None = None  # a selected structure in force
        self._structure_fit: dict | None = None
        self._S = wrench_matrix(self.model.geometry, self.alpha)
        self._Rinv = np.linalg.inv(hub_transfer_matrix(self.model.geometry))
        self._Mf = inertial_load_matrix(self.model)
        self._D = self.model.external.wrenches
        f = cfg.filter
        # issue 25: the harmonic states turn with the rotor's measured azimuth
        self.azimuth_mode = cfg.rotor.harmonic_phase == "azimuth"
        self.azimuth = AzimuthTracker(cfg.rotor.omega_nominal_rad_s, 1.0 / self.fs)
        self.azimuth_missing = 0  # samples advanced by the design's Ω (health)
        self.cache = design_cache(cfg, model=self.model)
        # a redesign takes 10-60 ms, longer than a sample: design the expected band now
        w0 = cfg.rotor.omega_nominal_rad_s
        try:
            self.cache.prefill(w0 * (1 - PREFILL_BAND), w0 * (1 + PREFILL_BAND))
            self.load_filter = LoadFilter(
                self.cache, self.alpha, invalid_after_samples=int(round(f.invalid_after_s * self.fs)),
                azimuth=self.azimuth_mode)
        except (np.linalg.LinAlgError, ValueError) as e:  # the config check (Nyquist) passed
            if isinstance(e, ConfigError):
                raise
            why = " ".join(f"{type(e).__name__}: {e}".split())
            raise ConfigError(
                "filter", f"harmonics {list(f.harmonics)}, time_constant_s {f.time_constant_s:g}",
                f"the load filter cannot be designed at rig.sample_rate_hz = {self.fs:g} and "
                f"rotor.omega_nominal_rad_s = {w0:g} ({why})",
                "use fewer or lower harmonics, a longer time_constant_s or a higher sample rate",
                cfg.source) from None
        # the filter's lag behind a moving static load: flag `transient` (estimator/transient.py)
        self.transient = TransientDetector(1.0 / self.fs,
                                           TIME_CONSTANT_FRACTION * f.time_constant_s)
        # the filter's own error σ (`sigma_filter`): its design's covariance plus what the
        # innovations show it does not follow (estimator/filter_sigma.py)
        self.filter_sigma = FilterSigma(
            1.0 / self.fs, f.time_constant_s,
            floor=noise_budget(self.model, cfg.identification.initial_angles_rad).total)
        self.cell_names = [c.name for c in cfg.cells]
        self.innov_every = max(1, int(round(self.fs / cfg.telemetry.innovations_hz)))
        # calibration branch
        idc = cfg.identification
        self.identification = identification
        # the identification worker died too often and is off (service): every hub_loads
        # record is flagged so
        self.identification_off = False
        self.period_n = int(round(idc.period_s * self.fs))
        self.window_n = int(round(idc.window_s * self.fs))
        self.apply_delay_n = int(round(idc.apply_delay_s * self.fs))
        self.buffer = WindowBuffer(self.window_n, 3 * len(cfg.accelerometers))
        # the inputs a sample may lack, as its flags name them (bit k of WindowBuffer.missing);
        # the last bit: unusable without a flag naming why (a non-finite reading)
        self.input_labels = input_labels(cfg)
        self._input_bit = {lab: k for k, lab in enumerate(self.input_labels[:-1])}
        omega0 = cfg.rotor.omega_nominal_rad_s
        harm = tuple(cfg.filter.harmonics)
        n_ch = 7 + 6 + 6
        self.content = {
            "known_loads": ContentFilter(idc.content_known_loads, self.fs, omega0, harm, n_ch),
            "filter_error": ContentFilter(idc.content_filter_error, self.fs, omega0, harm, n_ch),
        }
        self._hold = {"known_loads": MissingHold(), "filter_error": MissingHold()}
        self.first_seq: int | None = None
        self.last_known_seq: int | None = None
        self.pending: list[AnglesRecord] = []  # results waiting for their apply sample
        # results handed over (deliver: the service thread) and not yet scheduled: the
        # first step takes them in at its next sample (live, that step runs in the bus
        # thread; deque's append/popleft are atomic), so the sample a result applies from is
        # decided where samples are counted
        self._inbox: deque[tuple[AnglesRecord, int | None, bool]] = deque()
        self.outstanding: dict[int, int] = {}  # job id -> planned apply seq
        self.next_job_id = 0
        # a rotor speed whose highest modelled harmonic is at or above Nyquist cannot be
        # designed for (and no rotor gives one): such a reading is not used (model §5)
        self.omega_max = math.pi * self.fs / max(cfg.filter.harmonics)
        self.implausible_omega = 0  # readings refused (counted in health)
        self._last_seq: int | None = None
        self.design_errors = 0  # redesigns that failed: the current design was kept
        # stuck channels (a frozen sensor with a clean status, daq/runtime/stuck.py): flagged
        # fault:<cell|accelerometer> and treated like a faulted cell — predict-only (model
        # §6), H_static null, not ok in the identification window
        self.stuck = StuckMonitor(cfg, table) if cfg.stuck.enabled else None
        # how far the angles in force can move the hub loads (`sigma_angles`, flag
        # `angles_uncertain`; docs/identification.md): their covariance starts at the prior
        # (set_angles_covariance: a saved or recorded starting posterior), then each applied
        # angles record's P; flagged where it exceeds the static noise bound (`rsra
        # noise-budget`, model §4)
        n_a = len(self.model.geometry.angle_names)
        self._P_angles = np.eye(n_a) * cfg.identification.prior_sigma_rad ** 2
        self._angle_bound2 = noise_budget(self.model, idc.initial_angles_rad).total ** 2
        self._angle_var = HubAngleVariance(self.model.geometry, self.alpha, self._P_angles)
        self._sigma_angles = None  # the last measured sample's (predict-only samples keep it)
        self._angles_uncertain = False
        # the compiled hub path (daq/runtime/hubpath.py): measured samples' first step in one
        # call, the same records bit for bit; None: the reference path only (why: below)
        self.hub_kernel: HubKernel | None = None
        self.hub_kernel_status = "off (not asked)"
        if hub_kernel and self.azimuth_mode:  # the kernel's filter step is the design's Φ
            self.hub_kernel_status = "not used (rotor.harmonic_phase = azimuth)"
        elif hub_kernel:
            k, self.hub_kernel_status = load_hub_kernel()
            if k is not None:
                try:
                    self.hub_kernel = HubKernel(k, self)
                except ValueError as e:
                    self.hub_kernel_status = f"not used ({e})"

    # --- identification results -------------------------------------------------------
    def deliver(self, rec: AnglesRecord, arrival_seq: int | None = None,
                job_id: int | None = None) -> None:
        """Hand over an identification result of job ``job_id`` (live: ``arrival_seq`` given)
        or a recorded angles record (replay). Safe to call while another thread runs the first
        step of :meth:`stages`.

        Live: it applies from its planned sample, or — when the first step has passed that
        sample before taking the result in — from the first sample it takes it in at
        (`late`): after sample ``arrival_seq`` at the earliest. A recorded record carries its
        `applies_from_seq` and is applied exactly there; so is a lock-step result (no
        ``arrival_seq``: the loop waits for it).
        """
        planned = None
        if job_id is not None:
            planned = self.outstanding.pop(job_id, rec.get("applies_from_seq"))
        self._inbox.append((rec, planned, job_id is not None and arrival_seq is not None))

    def waiting_for(self, seq: int) -> list[int]:
        """Jobs whose result must be in before sample `seq` is processed (lock-step)."""
        return [j for j, s in self.outstanding.items() if s <= seq]

    def _take_in(self, seq: int) -> None:
        """The results handed over since the last sample, scheduled (before sample ``seq``)."""
        inbox = self._inbox
        while inbox:
            rec, planned, live = inbox.popleft()
            if planned is not None:
                if live and planned < seq:  # its sample has passed: from this one, late
                    rec = replace(rec, applies_from_seq=seq, late=True)
                else:
                    rec = replace(rec, applies_from_seq=planned,
                                  late=False if rec.late is ABSENT else rec.late)
            self.pending.append(rec)
            self.pending.sort(key=lambda r: r.applies_from_seq)

    def final_records(self, after_seq: int) -> list[AnglesRecord]:
        """At the end of a run: the results handed over that no sample applied — they apply
        from a sample after the last one (``after_seq``), i.e. to the next run through the
        state file the worker saved them to. Returned in order so that they are published and
        recorded like the others, and the run's summary and its saved posterior agree."""
        if self._inbox:
            self._take_in(after_seq + 1)
        out, self.pending = self.pending, []
        return out

    def _apply_due(self, seq: int, out: PipelineOutput) -> None:
        if self._inbox:
            self._take_in(seq)
        while self.pending and self.pending[0].applies_from_seq <= seq:
            rec = self.pending.pop(0)
            self.set_angles_covariance(rec.get("names"), rec.get("P"))
            if rec.accepted:
                names = rec.names or []
                alpha = self.alpha.copy()
                angle_names = self.model.geometry.angle_names
                for n, v in zip(names, rec.alpha):
                    if n in angle_names:
                        alpha[angle_names.index(n)] = v
                self.set_alpha(alpha)
            if rec.structure_fit is not ABSENT:  # known loads: the structure in force
                self.set_structure(rec.structure_fit)
            out.records.append(("angles", rec))

    def set_alpha(self, alpha: np.ndarray) -> None:
        self.alpha = np.asarray(alpha, float).copy()
        if self.structure is None:
            self._use_angles(self.alpha)

    def _use_angles(self, alpha: np.ndarray) -> None:
        self._S = wrench_matrix(self.model.geometry, alpha)
        self.load_filter.set_alpha(alpha)
        self._angle_var = HubAngleVariance(self.model.geometry, alpha, self._angles_P_in_force())

    def set_angles_covariance(self, names, P) -> None:
        """The covariance of the angles in force: the posterior ``P`` over ``names`` (an
        angles record's — every record carries the posterior whose mean is in force — or the
        starting posterior). Angles it does not name keep theirs; a record without P
        changes nothing."""
        if names is None or P is None:
            return
        P_new = angle_covariance(self.model.geometry.angle_names, names, P, self._P_angles)
        if not np.array_equal(P_new, self._P_angles):
            self._P_angles = P_new
            if self.structure is None:
                self._angle_var = HubAngleVariance(self.model.geometry, self.alpha, P_new)

    def _angles_P_in_force(self) -> np.ndarray:
        """Under a selected structure: its fit's α0 σ where the fit determined it (the prior
        σ elsewhere), its β's uncertainty left out; else the posterior's covariance."""
        if self.structure is None:
            return self._P_angles
        prior = self.cfg.identification.prior_sigma_rad
        sig = (self._structure_fit or {}).get("alpha0_sigma") or []
        n_a = len(self._P_angles)
        s = [float(sig[k]) if k < len(sig) and isinstance(sig[k], (int, float))
             and math.isfinite(sig[k]) else prior for k in range(n_a)]
        return np.diag(np.square(s))

    def set_structure(self, fit: dict | None) -> None:
        """Hub loads under a selected structure (estimator.structure.StructureCorrection:
        its angles and the correction of z), or under the constant angles again (None)."""
        if fit == self._structure_fit:
            return
        self._structure_fit = fit
        try:
            self.structure = None if fit is None else StructureCorrection(self.model, fit)
        except ValueError as e:  # a malformed record (another version): constant angles
            log.error("structure_fit not used (%s); hub loads use the constant angles", e)
            self.structure = None
        self._use_angles(self.alpha if self.structure is None else self.structure.alpha)

    # --- the per-sample path ----------------------------------------------------------
    def first_step_is_quick(self, s) -> bool:
        """The first step of sample ``s`` takes no slow work: no identification result to
        take in or apply (new angles redesign the filter: ms), no filter design for its rotor
        speed (a cache miss: 10–60 ms). Live, only such a step runs in the bus thread."""
        if self._inbox or (self.pending and self.pending[0].applies_from_seq <= int(s.seq)):
            return False
        omega = s.omega
        if omega is not None and not (math.isfinite(omega) and abs(omega) < self.omega_max):
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
        SYNC → hub-load latency path (docs/performance.md P5). Both steps must be taken, in
        order; live, the first runs in the bus thread and the second in the service thread
        (the first step of the next sample may run while this one's second runs: what the
        second needs of the first is passed in the generator's locals, never in ``self``)."""
        out = PipelineOutput()
        seq = int(s.seq)
        if self.first_seq is None:
            self.first_seq = seq
        self._apply_due(seq, out)
        alpha = self.alpha  # the angles in force for this sample (set_alpha replaces it)
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
            # (np.count_nonzero: a fraction of ndarray.all's cost on these short vectors, P5)
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
        if measured and not flags and self.hub_kernel is not None and self.structure is None:
            # the compiled hub path (daq/runtime/hubpath.py): the same records bit for bit;
            # None where this sample needs the reference path below
            fast = self.hub_kernel.first_step(s, seq, T, accel, q)
        if fast is not None:
            I, z, e, nis, omega, rec = fast
            out.records.append(("hub_loads", rec))
        else:
            I, z, e, nis, omega, dpsi = self._first_reference(s, seq, T, accel, q, flags,
                                                              measured, acc_ok, drive_ok, out)
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
            out.job = self._calibration_branch(s, seq, T, z, measured, omega, alpha, dpsi,
                                               flags)
        yield out

    def _first_reference(self, s, seq, T, accel, q, flags, measured, acc_ok, drive_ok,
                         out) -> tuple:
        """The first step's reference path (numpy): every sample the compiled hub path does
        not take, and all of them without it. Returns (I, z, e, nis, omega, dpsi)."""
        # (ndarray.dot: the same BLAS gemv as @, at half the call cost on these sizes, P5b)
        I = self._Mf.dot(accel) if acc_ok else np.full(6, np.nan)
        z = I - self._D.dot(q) if (q is not None and drive_ok) else I
        H_static = None
        zh = z if self.structure is None or not measured else self.structure.correct(z, T)
        if measured:
            H_static = self._Rinv.dot(zh - self._S.dot(T))
        omega = s.omega if s.omega is not None and math.isfinite(s.omega) else None
        refused = omega is not None and not abs(omega) < self.omega_max
        if refused:
            # a corrupt or impossible reading (e.g. 1e12 rad/s): no redesign for it — the
            # design would fail or take the estimator thread for tens of ms — and no value
            self.implausible_omega += 1
            omega = None
            node = f"missing:{self.cfg.rotor.node}"
            if node not in flags:
                flags.append(node)
        else:
            try:
                self.load_filter.set_omega(omega)
            except (ValueError, np.linalg.LinAlgError) as e:  # keep the current design
                self.design_errors += 1
                if self.design_errors == 1:
                    log.error("filter redesign at omega=%r failed (%s); the current design "
                              "is kept", omega, e)
        # samples lost before this one: SYNCs lost on the bus (lost_before), and samples
        # that never reached this step (a whole sample dropped from a full queue live,
        # counted in health; a replay's gap) — both keep their seq, so the gap says how far
        # to predict (model §6: Φ^k)
        lost = int(s.lost_before)
        if self._last_seq is not None and seq - self._last_seq - 1 > lost:
            lost = seq - self._last_seq - 1
        self._last_seq = seq
        dpsi = (self.azimuth.step(s.azimuth, omega, lost + 1) if self.azimuth_mode else None)
        res = self.load_filter.step(T if measured else np.zeros(7), zh if measured else np.zeros(6),
                                    measured=measured, lost=lost, dpsi=dpsi)
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
        if measured:  # (predict-only: H comes from earlier samples, and so does their σ)
            v = self._angle_var.variance(T)
            self._sigma_angles = np.sqrt(np.abs(v))
            self._angles_uncertain = np.count_nonzero(v > self._angle_bound2) > 0
        sigma_angles = None if res.H is None else self._sigma_angles
        if sigma_angles is not None and self._angles_uncertain:
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

    def _missing_bits(self, flags, measured: bool) -> int:
        m = 0
        for f in flags:  # (usually none)
            k = self._input_bit.get(f)
            if k is not None:
                m |= 1 << k
        if not measured and not m:
            m = 1 << (len(self.input_labels) - 1)
        return m

    def _calibration_branch(self, s, seq, T, z, measured, omega, alpha,
                            dpsi=None, flags=()) -> IdentJob | None:
        known = s.known_H is not None and bool(np.isfinite(np.asarray(s.known_H, float)).all())
        if known:
            self.last_known_seq = seq
        Hk = np.asarray(s.known_H, float) if known else np.zeros(6)
        x = np.concatenate([T if measured else np.zeros(7), z if measured else np.zeros(6), Hk])
        # one causal content filter per mode; both see every sample so either can take over.
        # A sample lacking an input enters as the last complete one, held (issue 29: the
        # identification leaves it out and uses the samples it has; estimator.content)
        xk = self._hold["known_loads"].input(x, measured and known)
        xf = self._hold["filter_error"].input(x, measured)
        hk = self.hub_kernel
        ck, cf = self.content["known_loads"], self.content["filter_error"]
        if hk is not None:  # the same sections in C (daq/runtime/hubpath.py), bit for bit
            yk, yf = hk.content_step(ck, xk), hk.content_step(cf, xf)
        else:
            yk, yf = ck.process(xk[None, :])[0], cf.process(xf[None, :])[0]
        fresh = self.last_known_seq is not None and seq - self.last_known_seq < self.fs * 0.5
        mode = "known_loads" if fresh else "filter_error"
        y = yk if mode == "known_loads" else yf
        if omega is None:
            omega = self.cfg.rotor.omega_nominal_rad_s
        self.buffer.add(seq, s.t, y[:7], y[7:13], y[13:], measured, known, omega, dpsi,
                        self._missing_bits(flags, measured) if flags or not measured else 0,
                        (x[:7], x[7:13]) if measured else None)
        since = seq - self.first_seq + 1
        if since < self.period_n or since % self.period_n != 0:
            return None
        w = self.buffer.window()
        if not self.azimuth_mode:
            w.pop("dpsi")
        job_id = self.next_job_id
        self.next_job_id += 1
        planned = int(w["seq"][-1]) + self.apply_delay_n
        self.outstanding[job_id] = planned
        content = (self.cfg.identification.content_known_loads if mode == "known_loads"
                   else self.cfg.identification.content_filter_error)
        return IdentJob(job_id=job_id, mode=mode, content=content, applies_from_seq=planned,
                        alpha=alpha.copy(), **w)
