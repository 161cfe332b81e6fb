"""Stuck-channel detection: a sensor that keeps sending the same value (a frozen ADC, a
hung converter, a node repeating its last process image) while its status stays clean.

The test is the one a frozen channel cannot pass and an honest one almost never fails: the
raw value repeats *exactly* for k consecutive samples. k is chosen per channel from its
configured noise σ and its quantum q (the value's LSB in engineering units, from the EDS
data type of the mapped object and the channel's scale and calibration gain), so that an
honest channel at rest — the worst case: a constant true value plus white Gaussian noise
(model §4's σ) — raises a false alarm with probability below ``stuck.false_alarm_per_hour``
per channel-hour.

Why that probability. At rest the reading is x_n = Q(μ + σ ε_n), ε_n independent N(0, 1),
Q the rounding to the grid of step q. Let P_j be the probability of grid level j. k
consecutive readings are all equal with probability

    p_k(μ) = Σ_j P_j^k                                           (exact: the ε_n are independent)

(the worst case over the offset μ of the true value on the grid is taken). An alarm at
sample n needs such a run ending at n, so over N = 3600·f_s samples an hour the probability
of any false alarm is at most N·p_k (union bound). k is the smallest run length with
N·p_k ≤ the configured rate. For σ ≫ q the sum is a Riemann sum of φ^k:
p_k = (q/σ)^(k−1) (2π)^(−(k−1)/2) k^(−1/2) (used above σ/q = ASYMPTOTIC_RATIO; the two agree
there to 1e-4 relative, tests/test_stuck.py). A channel that needs k > stuck.max_delay_s·f_s
(its noise is not above its quantum: σ ≲ q/2 at the defaults) cannot be told from a stuck
one in time: it is *untested* and listed as such (health ``estimator.stuck_untested``),
never flagged.

Scope: load-cell forces and accelerometer axes (the measurement of model §6). Not the rotor
speed (a stopped rotor reads exactly 0 for ever), not the status bytes, not the balance.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr

from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import DecodeTable

SECONDS_PER_HOUR = 3600.0
ASYMPTOTIC_RATIO = 50.0  # σ/q above which the Riemann-sum limit is used (exact sum costs ~σ/q)
OFFSETS = 64  # grid offsets μ/q searched for the worst case
MANTISSA_BITS = {"f": 23, "d": 52}  # REAL32, REAL64 (IEEE 754)


def quantum(code: str, gain: float, full_scale: float, offset: float = 0.0) -> float:
    """The LSB of a channel in engineering units: ``gain`` (scale × calibration gain) times
    the raw step — 1 for an integer type; for a float type the spacing of representable
    numbers at the largest raw value the channel reaches (|full scale − offset| / |gain|),
    the coarsest it gets."""
    g = abs(gain)
    if code not in MANTISSA_BITS:
        return g
    raw_max = abs(full_scale - offset) / g if g > 0 else 0.0
    if raw_max <= 0 or not math.isfinite(raw_max):
        return g * math.ulp(1.0)
    return g * 2.0 ** (math.floor(math.log2(raw_max)) - MANTISSA_BITS[code])


def run_probability(sigma: float, q: float, k: int) -> float:
    """p_k: the largest, over the true value's offset on the grid, probability that k
    consecutive readings of an honest channel at rest (noise σ, quantum q) are equal."""
    if k < 2:
        return 1.0
    if sigma <= 0:
        return 1.0
    r = sigma / q
    if r > ASYMPTOTIC_RATIO:
        return math.exp(-(k - 1) * math.log(r) - 0.5 * (k - 1) * math.log(2 * math.pi)
                        - 0.5 * math.log(k))
    return float(np.max(_exact_runs(sigma, q, k)))


def _exact_runs(sigma: float, q: float, k: int) -> np.ndarray:
    """Σ_j P_j^k for OFFSETS offsets μ ∈ [0, q/2] (the sum is even and q-periodic in μ)."""
    half = int(math.ceil(10.0 * sigma / q)) + 2
    j = np.arange(-half, half + 1)[None, :]
    mu = np.linspace(0.0, 0.5, OFFSETS)[:, None]
    P = ndtr(((j + 0.5) - mu) * q / sigma) - ndtr(((j - 0.5) - mu) * q / sigma)
    return (P ** k).sum(axis=1)


def run_length(sigma: float, q: float, fs: float, false_alarm_per_hour: float,
               k_max: int) -> int | None:
    """The smallest k ≥ 2 with 3600·fs·p_k ≤ the rate; None when that needs k > k_max."""
    n_hour = SECONDS_PER_HOUR * fs
    for k in range(2, max(2, k_max) + 1):
        if n_hour * run_probability(sigma, q, k) <= false_alarm_per_hour:
            return k
    return None


@dataclass(frozen=True)
class StuckChannel:
    key: str  # "<node>.<channel>"
    flag: str  # what the sample carries while it is stuck
    sigma: float  # configured noise, engineering units
    q: float  # quantum, engineering units
    k: int | None  # run length that flags it; None: untested
    false_alarm_per_hour: float  # 3600 fs p_k at that k (the bound achieved)


def plan(cfg: RigConfig, table: DecodeTable | None = None) -> tuple[StuckChannel, ...]:
    """The tested channels in the pipeline's order: the seven cell forces (cfg.cells order),
    then x, y, z of every accelerometer. A stuck cell is flagged ``fault:<cell>`` and treated
    like a cell reporting a sensor fault (model §6: predict-only). A stuck accelerometer axis
    is flagged ``fault:<accelerometer>`` (its [[accelerometers]] name) and treated the same:
    the inertial loads need every axis. Not ``missing:<node>``: the node did report (its
    values are in ``channels``, and health's ``samples.incomplete`` counts only nodes that
    did not)."""
    table = table or DecodeTable(cfg)
    st = cfg.stuck
    fs = cfg.sample_rate_hz
    k_max = int(round(st.max_delay_s * fs))
    codes: dict[int, str] = {}
    for lay in table.tpdos.values():
        for i in range(lay.start, lay.stop):
            codes[i] = lay.codes[i - lay.start]
    out = []

    def add(key: str, flag: str, sigma: float, full_scale: float) -> None:
        i = table.index(key)
        q = quantum(codes[i], float(table.gain[i]), full_scale, float(table.offset[i]))
        k = run_length(sigma, q, fs, st.false_alarm_per_hour, k_max)
        rate = SECONDS_PER_HOUR * fs * run_probability(sigma, q, k) if k else float("nan")
        out.append(StuckChannel(key, flag, sigma, q, k, rate))

    for c in cfg.cells:
        add(f"{c.node}.force", f"fault:{c.name}", c.sigma_N, c.full_scale_N)
    from rsra.config.rig import G0

    for a in cfg.accelerometers:
        for axis in "xyz":
            add(f"{a.node}.{axis}", f"fault:{a.name}", a.sigma_m_s2, a.full_scale_g * G0)
    return tuple(out)


class StuckDetector:
    """Per channel: the length of the current run of exactly equal readings (vectorised;
    state is two numbers per channel). A channel is stuck on every sample whose run has
    reached its k, and clear again on the first sample whose value differs. A missing reading
    (NaN) neither extends nor ends a run, and is not flagged (it is missing already)."""

    def __init__(self, k: np.ndarray | Sequence[int]):
        self.k = np.asarray(k, np.int64)  # 0: untested
        n = len(self.k)
        self.tested = self.k > 0
        # the run length that flags, an untested channel's never reached (one compare a sample)
        self._k_flag = np.where(self.tested, self.k, np.iinfo(np.int64).max)
        self._value = np.full(n, np.nan)
        self._run = np.zeros(n, np.int64)
        # after samples that took the shortcut in Python (update_fresh): the last one's
        # readings; the arrays above are brought up to date only when read or when a sample
        # takes the vectorised path (a dozen numpy calls saved on the per-sample path)
        self._last: list[float] | None = None
        self.episodes = np.zeros(n, np.int64)  # runs that reached k
        self.samples = np.zeros(n, np.int64)  # samples flagged
        self.stuck = np.zeros(n, bool)
        self.n_stuck: int | np.integer[Any] = 0  # channels stuck in the last sample
        self.fresh = False  # the last sample took the shortcut below (every reading present)
        # the common sample — every reading present and new — restarts every run at 1, and
        # flags nothing when no channel flags at a run of 1: then it is three ufuncs and
        # two copies (the estimator's per-sample path)
        self._fresh_ok = bool(n) and int(self._k_flag.min()) >= 2
        self._none = np.zeros(n, bool)
        self._none.flags.writeable = False

    @property
    def value(self) -> np.ndarray:
        """Per channel, the value of its current run (NaN before the first reading)."""
        self._settle()
        return self._value

    @property
    def run(self) -> np.ndarray:
        """Per channel, the length of its current run of equal readings."""
        self._settle()
        return self._run

    def _settle(self) -> None:
        if self._last is not None:  # the last sample was new and present on every channel
            self._run.fill(1)
            self._value[:] = self._last
            self._last = None

    def update_fresh(self, xl: list[float]) -> bool:
        """The common sample, as Python floats: when every reading is present and differs
        from the last one (every run restarts at 1, nothing flags), take it and return True
        (``fresh``) — with no numpy call; otherwise change nothing and return False (then
        :meth:`update` takes it). The same decision as :meth:`update`'s shortcut."""
        if not self._fresh_ok:
            return False
        prev = self._last if self._last is not None else self._value.tolist()
        for a, b in zip(xl, prev):
            if a == b or a - a != 0.0:  # the same, or not finite (a - a is NaN for inf, NaN)
                return False
        self._last = xl
        self.stuck = self._none
        self.n_stuck = 0
        self.fresh = True
        return True

    def update(self, x: np.ndarray, explained: np.ndarray | None = None) -> np.ndarray:
        """Feed one sample's readings; returns the channels stuck in it. ``explained``: the
        channels whose own status already accounts for a constant value (an over-range cell
        reads full scale): their run goes on, but they are not flagged or counted."""
        self._settle()
        x = np.asarray(x, float)
        if self._fresh_ok:
            same = x == self.value
            if not np.count_nonzero(same):
                if np.count_nonzero(np.isfinite(x)) == x.size:
                    self._run.fill(1)
                    self._value[:] = x
                    self.stuck = self._none
                    self.n_stuck = 0
                    self.fresh = True
                    return self._none
        self.fresh = False
        present = np.isfinite(x)
        same = x == self.value  # NaN equals nothing: a repeat is always a present reading
        new = present ^ same  # present and different: a new run starts at 1
        # in place (the estimator's per-sample path)
        run = self._run
        run += same
        np.copyto(run, 1, where=new)
        np.copyto(self._value, x, where=new)
        stuck = present & (run >= self._k_flag)
        if explained is not None:
            stuck &= ~np.asarray(explained, bool)
        self.n_stuck = n_stuck = np.count_nonzero(stuck)  # (ndarray.any costs 4x as much)
        if n_stuck:
            self.episodes += stuck & (run == self.k)
            self.samples += stuck
        self.stuck = stuck
        return stuck


class StuckMonitor:
    """The detector for a rig, with the flags each stuck channel puts on the sample."""

    def __init__(self, cfg: RigConfig, table: DecodeTable | None = None):
        self.channels = plan(cfg, table)
        self.detector = StuckDetector([c.k or 0 for c in self.channels])
        self.keys = [c.key for c in self.channels]
        self.n_cells = len(cfg.cells)
        self.untested = [c.key for c in self.channels if c.k is None]
        self._x = np.empty(len(self.channels))

    def update(self, T: np.ndarray, accel: np.ndarray, flags: tuple[str, ...] | list[str] = ()
               ) -> list[str]:
        """The flags of this sample (each once, in channel order). ``flags``: the sample's
        own; a cell that reports over-range or a fault by its status is not flagged stuck
        (the simulated over-range pins the force at full scale: one cause, one flag)."""
        if not flags and isinstance(T, np.ndarray) and T.ndim == 1 and self._acc_flat(accel):
            # the common sample in Python: present and new everywhere (nothing can flag)
            xl = T.tolist()
            xl += accel.ravel().tolist()
            if self.detector.update_fresh(xl):
                return []
        x = self._x  # reused: the detector keeps only copies of it
        x[:self.n_cells] = np.asarray(T, float).reshape(-1)
        x[self.n_cells:] = np.asarray(accel, float).reshape(-1)
        hit = self.detector.update(x, self._explained(flags) if flags else None)
        if not self.detector.n_stuck:
            return []
        return list(dict.fromkeys(self.channels[i].flag for i in np.flatnonzero(hit)))

    def _explained(self, flags: tuple[str, ...] | list[str]) -> np.ndarray | None:
        """The cells whose status (over-range, fault) explains a held value, or None."""
        status = {f.split(":", 1)[1] for f in flags if f.startswith(("overrange:", "fault:"))}
        if not status:
            return None
        return np.array([c.flag.split(":", 1)[1] in status and i < self.n_cells
                         for i, c in enumerate(self.channels)])

    def _acc_flat(self, accel: np.ndarray) -> bool:
        return isinstance(accel, np.ndarray) and accel.size + self.n_cells == len(self._x)

    def health(self) -> dict:
        """Counts for the health record (estimator.stuck_*)."""
        d = self.detector
        return {"stuck_samples": int(d.samples.sum()), "stuck_episodes": int(d.episodes.sum()),
                "stuck_now": [self.keys[i] for i in np.flatnonzero(d.stuck)],
                "stuck_untested": list(self.untested)}
