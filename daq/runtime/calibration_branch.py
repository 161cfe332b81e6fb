"""The estimator pipeline's calibration branch (daq/runtime/pipeline.py; docs/architecture.md,
the data flow): each sample's cell loads, inertial loads and known loads through a causal
content filter per mode, into a window buffer, and every ``period_s`` the last ``window_s``
of it as an identification job (records.IdentJob) for the worker.
"""
from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.runtime.reasons import input_labels
from rsra.daq.runtime.records import IdentJob
from rsra.daq.runtime.result_schedule import ResultSchedule
from rsra.estimator.content import ContentFilter, MissingHold


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
        # what each sample lacked (bits of CalibrationBranch.input_labels): reported in a
        # rejected run's explanation (daq.runtime.reasons), never used to decide
        self.missing = np.zeros(n, dtype=np.uint64)
        # the raw (not content-filtered) cell loads and z: the window's mean static load, for
        # the filter-error load excursion (the angles' move with the load away from trim)
        self.T_raw = np.zeros((n, 7))
        self.z_raw = np.zeros((n, 6))
        self.count = 0

    def add(self, seq: int, t: float, T: np.ndarray, z: np.ndarray, H: np.ndarray, ok: bool,
            known: bool, omega: float, dpsi: float | None = None, missing: int = 0,
            raw: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        i = self.count % self.n
        self.T[i], self.z[i], self.H[i] = T, z, H
        if raw is not None:
            self.T_raw[i], self.z_raw[i] = raw
        self.dpsi[i] = np.nan if dpsi is None else dpsi
        self.seq[i], self.t[i], self.ok[i], self.known[i], self.omega[i] = seq, t, ok, known, omega
        self.missing[i] = missing
        self.count += 1

    def window(self) -> dict[str, Any]:
        """The last n samples in time order (copies: the job leaves this thread)."""
        m = min(self.count, self.n)
        idx = (np.arange(self.count - m, self.count)) % self.n
        return {"T": self.T[idx].copy(), "z": self.z[idx].copy(), "known_H": self.H[idx].copy(),
                "seq": self.seq[idx].copy(), "t": self.t[idx].copy(), "ok": self.ok[idx].copy(),
                "known": self.known[idx].copy(), "omega": self.omega[idx].copy(),
                "dpsi": self.dpsi[idx].copy(),
                "missing": self.missing[idx].copy(),
                **self._raw_means(idx)}

    def _raw_means(self, idx: np.ndarray) -> dict[str, Any]:
        """The window's mean raw cell loads and z over its complete samples (None: none)."""
        ok = self.ok[idx]
        if not ok.any():
            return {"T_mean": None, "z_mean": None}
        return {"T_mean": self.T_raw[idx][ok].mean(axis=0),
                "z_mean": self.z_raw[idx][ok].mean(axis=0)}


class ContentStep(Protocol):
    """One sample through a content filter (the compiled hub path's, hubpath.HubKernel)."""

    def content_step(self, cf: ContentFilter, x: np.ndarray) -> np.ndarray: ...


class CalibrationBranch:
    """The calibration branch: per sample (:meth:`step`) the content filters of both modes
    (known loads while the balance is fresh, else filter error), the window buffer, and every
    ``period_n`` samples an identification job, planned in ``schedule`` to apply
    ``apply_delay_n`` samples after its window."""

    def __init__(self, cfg: RigConfig, schedule: ResultSchedule) -> None:
        idc = cfg.identification
        self.fs = cfg.sample_rate_hz
        self.omega_nominal = cfg.rotor.omega_nominal_rad_s
        self.azimuth_mode = cfg.rotor.harmonic_phase == "azimuth"
        self.schedule = schedule
        self.period_n = int(round(idc.period_s * self.fs))
        self.window_n = int(round(idc.window_s * self.fs))
        self.apply_delay_n = int(round(idc.apply_delay_s * self.fs))
        self.buffer = WindowBuffer(self.window_n, 3 * len(cfg.accelerometers))
        # the inputs a sample may lack, as its flags name them (bit k of WindowBuffer.missing);
        # the last bit: unusable without a flag naming why (a non-finite reading)
        self.input_labels = input_labels(cfg)
        self._input_bit = {lab: k for k, lab in enumerate(self.input_labels[:-1])}
        harm = tuple(cfg.filter.harmonics)
        n_ch = 7 + 6 + 6
        self.kinds = {"known_loads": idc.content_known_loads,
                      "filter_error": idc.content_filter_error}
        self.content = {mode: ContentFilter(kind, self.fs, self.omega_nominal, harm, n_ch)
                        for mode, kind in self.kinds.items()}
        self._hold = {"known_loads": MissingHold(), "filter_error": MissingHold()}
        self.last_known_seq: int | None = None

    def missing_bits(self, flags: Any, measured: bool) -> int:
        """The inputs a sample lacked (bits of ``input_labels``), from its flags."""
        m = 0
        for f in flags:  # (usually none)
            k = self._input_bit.get(f)
            if k is not None:
                m |= 1 << k
        if not measured and not m:
            m = 1 << (len(self.input_labels) - 1)
        return m

    def step(self, s: Any, seq: int, since: int, T: np.ndarray, z: np.ndarray, measured: bool,
             omega: float | None, alpha: np.ndarray, dpsi: float | None = None,
             flags: Any = (), kernel: ContentStep | None = None) -> IdentJob | None:
        """Sample ``s`` (number ``seq``, the ``since``-th of the run) into the branch: its
        cell loads ``T`` and inertial loads ``z`` (used when ``measured``), its known loads;
        returns the identification job when one is due (cut with the angles ``alpha``).
        ``kernel``: the compiled content-filter step, else numpy's."""
        known = s.known_H is not None and bool(np.isfinite(np.asarray(s.known_H, float)).all())
        if known:
            self.last_known_seq = seq
        Hk = np.asarray(s.known_H, float) if known else np.zeros(6)
        x = np.concatenate([T if measured else np.zeros(7), z if measured else np.zeros(6), Hk])
        # one causal content filter per mode; both see every sample so either can take over.
        # A sample lacking an input enters as the last complete one, held (so the filters
        # keep running; the identification leaves the sample out and uses the ones it has,
        # estimator.content)
        xk = self._hold["known_loads"].input(x, measured and known)
        xf = self._hold["filter_error"].input(x, measured)
        ck, cf = self.content["known_loads"], self.content["filter_error"]
        # a short gap just closed: the filters continue as if it had been interpolated
        for hold, content in ((self._hold["known_loads"], ck), (self._hold["filter_error"], cf)):
            correction = hold.correction()
            if correction is not None:
                content.correct_past_inputs(correction)
        if kernel is not None:  # the same sections in C (daq/runtime/hubpath.py), bit for bit
            yk, yf = kernel.content_step(ck, xk), kernel.content_step(cf, xf)
        else:
            yk, yf = ck.process(xk[None, :])[0], cf.process(xf[None, :])[0]
        fresh = self.last_known_seq is not None and seq - self.last_known_seq < self.fs * 0.5
        mode = "known_loads" if fresh else "filter_error"
        y = yk if mode == "known_loads" else yf
        if omega is None:
            omega = self.omega_nominal
        self.buffer.add(seq, s.t, y[:7], y[7:13], y[13:], measured, known, omega, dpsi,
                        self.missing_bits(flags, measured) if flags or not measured else 0,
                        (x[:7], x[7:13]) if measured else None)
        if since < self.period_n or since % self.period_n != 0:
            return None
        w = self.buffer.window()
        if not self.azimuth_mode:
            w.pop("dpsi")
        planned = int(w["seq"][-1]) + self.apply_delay_n
        job_id = self.schedule.plan(planned)
        return IdentJob(job_id=job_id, mode=mode, content=self.kinds[mode],
                        applies_from_seq=planned, alpha=alpha.copy(), **w)
