"""The tare with the rotor stopped and no applied load (`rsra zero`; docs/cli.md §11;
docs/bus.md §1; model.md §3).

The command (:mod:`rsra.daq.cli.commands.zero`) boots the nodes like the service (normal master); this
module averages every calibrated channel over
``--seconds`` of acquisition time and writes new zero offsets as a ``[calibration]`` TOML
fragment (``"<node>.<channel>" = { gain = …, offset = … }``, the table rsra.config.rig reads).

What each channel reads at rest after the tare (its *target*):

* accelerometers: the gravity vector in body axes, ``f = a − g = (0, 0, −g)`` (z down;
  docs/bus.md §1: at rest, level, z reads −1000 mg). Gravity stays in the readings because the
  balance ``I = S T + R H`` (model §3, report Eq 1.1) carries it on both sides: the
  inertial load ``I = m f`` of the resting transmission is its weight. Assumes a level rig.
* load cells: their dead-weight reactions, NOT zero. At rest the cells carry the weight, so
  ``S(α) T = I`` with ``H = 0``. Zeroing the cells while the accelerometers keep −1 g would
  make the static estimate ``Ĥ = R⁻¹(I − S T)`` (Eq 1.2) read the weight (≈ m_z g) as a
  hub load. The tare removes the smallest σ-weighted correction ``b`` (7 cells, 6 equations)
  with ``S(α)(T̄ − b) = I_target``, so ``Ĥ`` of the rest readings is zero; the part of the
  readings no hub load can explain (the one self-stress state of seven cells, the null space
  of S) is left as measured.
* rotor speed, reference-balance loads, drive loads: 0.
* not tared (kept as configured): the azimuth (its zero is the blade reference, which a
  stopped rotor does not give), status bytes (bit fields), channels of absent nodes.

It refuses (exit 1) when the data show the rotor turning (Ω above ``omega_min``), a load
(a σ above the configured sensor σ at a 10⁻³ false-alarm rate over all tested channels, or a
zero shift larger than ``--max-offset-fs`` of full scale), a load-cell status bit, or too
few samples.
"""
from __future__ import annotations

import itertools
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime, timezone
from collections.abc import Iterator
from typing import Any, Callable

import numpy as np
from scipy.stats import chi2

from rsra.config.rig import G0, RigConfig
from rsra.daq.bus.decoder import DecodeTable

# At rest the accelerometers read f = a − g = −g: (0, 0, −g) in body axes with z down.
GRAVITY_AT_REST = np.array([0.0, 0.0, -G0])
FALSE_ALARM = 1e-3  # the σ test: probability of refusing a good tare (all channels together)
DEFAULT_SECONDS = 10.0
# The tare's own error is σ/√n; 100 samples keep it at 10 % of the sensor σ.
DEFAULT_MIN_SAMPLES = 100
# Zero balance of a strain-gauge load cell is typically within ±1 % of rated output (and a
# MEMS accelerometer's bias well inside 1 % of a 7 g range): a shift of more than 2 % of full
# scale is an applied load, a tilted rig or a damaged sensor, not a zero offset to adopt.
DEFAULT_MAX_OFFSET_FS = 0.02
STALL_S = 2.0  # no sample for this long (wall clock) once started: the acquisition stalled
FT_M = 0.3048


@dataclass(frozen=True)
class ChannelSpec:
    """One channel the tare averages."""

    key: str  # "<node>.<channel>"
    kind: str  # "cell", "accel", "omega", "balance", "drive"
    quantity: str  # "force", "moment", "accel", "rate" (display units)
    required: bool  # its node is required
    sigma: float | None  # configured sensor σ (accuracy × full scale), for the load test
    limit: float | None  # largest credible zero shift (max_offset_fs × full scale)
    target: float | None  # reading at rest; None for load cells (from the balance)
    gain: float  # current calibration
    offset: float


@dataclass
class ChannelResult:
    spec: ChannelSpec
    n: int
    mean: float
    std: float
    max_abs: float
    target: float
    new_offset: float

    @property
    def shift(self) -> float:
        """target − mean: how far the tare moves this channel's reading."""
        return self.target - self.mean


@dataclass
class TareResult:
    channels: list[ChannelResult]
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    hub_loads_now: np.ndarray | None = None  # Ĥ of the means before the tare (info)
    samples: int = 0
    span_s: float = 0.0
    omega_max: float | None = None

    @property
    def ok(self) -> bool:
        return not self.problems


def channel_specs(cfg: RigConfig, table: DecodeTable,
                  max_offset_fs: float = DEFAULT_MAX_OFFSET_FS) -> list[ChannelSpec]:
    """Every calibrated channel the estimator uses, in sample order: the seven load cells,
    each accelerometer's x y z, Ω, the balance X…N, the drive loads."""
    specs: list[ChannelSpec] = []
    for key, kind, quantity, sigma, full_scale, target in itertools.chain(
            _cell_rows(cfg), _accel_rows(cfg), _omega_rows(cfg), _balance_rows(cfg),
            _drive_rows(cfg, table)):
        if not table.has_channel(key):
            from rsra.config.rig import ConfigError
            raise ConfigError("nodes", key.split(".")[0], f"the EDS maps no channel {key!r}",
                              "use the EDS of the role's device profile (docs/bus.md §1)")
        node = cfg.node(key.split(".")[0])
        gain, offset = cfg.calibration.get(key, (1.0, 0.0))
        specs.append(ChannelSpec(key, kind, quantity, bool(node and node.required), sigma,
                                 None if full_scale is None else max_offset_fs * full_scale,
                                 target, float(gain), float(offset)))
    return specs


# (key, kind, quantity, sensor σ, full scale, target at rest) of each kind of channel, in
# sample order
_Row = tuple[str, str, str, float | None, float | None, float | None]


def _cell_rows(cfg: RigConfig) -> Iterator[_Row]:
    for c in cfg.cells:
        yield f"{c.node}.force", "cell", "force", c.sigma_N, c.full_scale_N, None


def _accel_rows(cfg: RigConfig) -> Iterator[_Row]:
    for a in cfg.accelerometers:
        for j, ax in enumerate("xyz"):
            yield (f"{a.node}.{ax}", "accel", "accel", a.sigma_m_s2, a.full_scale_g * G0,
                   float(GRAVITY_AT_REST[j]))


def _omega_rows(cfg: RigConfig) -> Iterator[_Row]:
    if cfg.rotor.node:
        yield f"{cfg.rotor.node}.omega", "omega", "rate", None, None, 0.0


def _balance_rows(cfg: RigConfig) -> Iterator[_Row]:
    b = cfg.balance
    if not b.node:
        return
    for j, ax in enumerate("XYZLMN"):
        fs = b.full_scale_force_N if j < 3 else b.full_scale_moment_Nm
        yield (f"{b.node}.{ax}", "balance", "force" if j < 3 else "moment", float(b.sigma[j]),
               fs, 0.0)


def _drive_rows(cfg: RigConfig, table: DecodeTable) -> Iterator[_Row]:
    for e in cfg.external_loads:
        nl = table.node(e.node)
        keys = [c.key for c in table.channels[nl.start:nl.stop] if not c.is_status]
        yield keys[0], "drive", "moment", e.sigma, None, 0.0


def extractor(cfg: RigConfig, specs: list[ChannelSpec]) -> Callable[[Any], np.ndarray]:
    """sample -> one row of channel values in ``specs`` order (nan where missing)."""
    n_cells, K = len(cfg.cells), len(cfg.accelerometers)
    i_omega = [i for i, s in enumerate(specs) if s.kind == "omega"]
    i_bal = [i for i, s in enumerate(specs) if s.kind == "balance"]
    i_drv = [i for i, s in enumerate(specs) if s.kind == "drive"]
    a0 = n_cells

    def row(s: Any) -> np.ndarray:
        r = np.full(len(specs), np.nan)
        r[:n_cells] = s.T
        r[a0:a0 + 3 * K] = np.asarray(s.accel, float).reshape(-1)
        if i_omega and s.omega is not None:
            r[i_omega[0]] = s.omega
        if i_bal and s.known_H is not None:
            r[i_bal] = s.known_H
        if i_drv and s.drive is not None:
            r[i_drv] = s.drive
        return r

    return row


def _sigma_factor(n: int, m: int, false_alarm: float) -> float:
    """Largest sample σ / true σ of white noise over n samples, m channels tested together:
    (n−1) s²/σ² ~ χ²(n−1), Bonferroni over the channels."""
    return math.sqrt(float(chi2.ppf(1.0 - false_alarm / max(m, 1), n - 1)) / (n - 1))


@dataclass(frozen=True)
class _Stats:
    """Per channel of one rest recording (nan where a channel has no sample)."""

    n: np.ndarray  # samples
    mean: np.ndarray
    std: np.ndarray
    max_abs: np.ndarray

    @classmethod
    def of(cls, values: np.ndarray) -> "_Stats":
        C = values.shape[1]
        finite = np.isfinite(values)
        n = finite.sum(axis=0)
        safe = np.where(finite, values, 0.0)
        mean = np.divide(safe.sum(axis=0), n, out=np.full(C, np.nan), where=n > 0)
        dev = np.where(finite, values - mean, 0.0)
        std = np.divide(np.sqrt((dev**2).sum(axis=0)), np.sqrt(np.maximum(n - 1, 1)),
                        out=np.full(C, np.nan), where=n > 1)
        max_abs = np.where(n > 0, np.max(np.abs(safe), axis=0, initial=0.0), np.nan)
        return cls(n, mean, std, max_abs)


def _cell_targets(cfg: RigConfig, specs: list[ChannelSpec], st: _Stats, alpha: np.ndarray,
                  target: np.ndarray, res: TareResult) -> None:
    """The load cells' targets: the smallest σ-weighted correction b with S(α)(T̄ − b) = I
    at rest (Eq 1.1 with H = 0, D q = 0); I = M_f f with every accelerometer at its target
    −g. With the accelerometers too, what the rig reads now (info): Ĥ = R⁻¹(I − S T̄)."""
    from rsra.estimator.balance import inertial_load_matrix
    from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix

    cells = [i for i, s in enumerate(specs) if s.kind == "cell"]
    accs = [i for i, s in enumerate(specs) if s.kind == "accel"]
    if not np.all(st.n[cells] > 0):
        return
    model = cfg.rig_model()
    S = wrench_matrix(model.geometry, alpha)
    Mf = inertial_load_matrix(model)
    I_target = Mf @ np.tile(GRAVITY_AT_REST, len(cfg.accelerometers))
    T_bar = st.mean[cells]
    W = np.diag(np.array([specs[i].sigma for i in cells]) ** 2)
    b = W @ S.T @ np.linalg.solve(S @ W @ S.T, S @ T_bar - I_target)
    tc = T_bar - b
    # round-off of an exact zero (a cell no weight reaches) is shown as 0
    target[cells] = np.where(np.abs(tc) < 1e-12 * np.abs(T_bar).max(initial=1.0), 0.0, tc)
    if np.all(st.n[accs] > 0):
        R = hub_transfer_matrix(model.geometry)
        res.hub_loads_now = np.linalg.solve(R, Mf @ st.mean[accs] - S @ T_bar)


# -- refusals (problems) and notes, each check on its own -------------------------------

def _few_samples(specs: list[ChannelSpec], st: _Stats, min_samples: int, res: TareResult
                 ) -> None:
    few = [f"{s.key} {st.n[i]}" for i, s in enumerate(specs)
           if st.n[i] < min_samples and (s.required or st.n[i] > 0)]
    if few:
        res.problems.append(f"too few samples ({', '.join(few)}; need {min_samples}): acquire "
                            "longer (--seconds) or check the bus")
    absent = sorted({s.key.split(".")[0] for i, s in enumerate(specs) if st.n[i] == 0
                     and not s.required})
    res.notes += [f"optional node {node} sent no data: its channels are not tared"
                  for node in absent]


def _rotor_turning(cfg: RigConfig, specs: list[ChannelSpec], st: _Stats, res: TareResult
                   ) -> None:
    omega_min = cfg.rotor.omega_min_fraction * cfg.rotor.omega_nominal_rad_s
    for i, s in enumerate(specs):
        if s.kind != "omega" or st.n[i] == 0:
            continue
        res.omega_max = float(st.max_abs[i])
        if st.max_abs[i] > omega_min:
            res.problems.append(
                f"the rotor is turning: {s.key} reaches {st.max_abs[i]:.3g} rad/s, above "
                f"omega_min = {omega_min:.3g} rad/s (rotor.omega_min_fraction × "
                "omega_nominal_rad_s); stop the rotor")
    if cfg.rotor.node and res.omega_max is None:
        res.notes.append("no rotor-speed data: make sure the rotor is stopped")


def _status_bits(status_counts: dict[str, int], res: TareResult) -> None:
    for flag, count in sorted(status_counts.items()):
        kind, _, cell = flag.partition(":")
        what = "over-range" if kind == "overrange" else "a sensor fault"
        res.problems.append(f"load cell {cell} reported {what} in {count} samples: fix the "
                            "cell before taring")


def _varying(specs: list[ChannelSpec], st: _Stats, false_alarm: float, res: TareResult
             ) -> None:
    """A channel whose σ exceeds its sensor's at the false-alarm rate (all tested together)."""
    tested = [(i, s, s.sigma) for i, s in enumerate(specs) if s.sigma is not None and st.n[i] > 1]
    for i, s, sigma in tested:
        limit = sigma * _sigma_factor(int(st.n[i]), len(tested), false_alarm)
        if st.std[i] > limit:
            res.problems.append(
                f"{s.key} varies: σ = {st.std[i]:.4g} exceeds {limit:.4g} (the configured "
                f"sensor σ {sigma:.4g} at a {false_alarm:g} false-alarm rate): a varying load "
                "(shaker, wind, someone on the rig), vibration or a noisy sensor")


_SHIFT_CAUSES = {"cell": "a load is applied or the cell is faulty",
                 "accel": "the rig is not level, moving, or the accelerometer is faulty",
                 "balance": "a load is applied to the hub"}


def _big_shifts(specs: list[ChannelSpec], st: _Stats, target: np.ndarray, res: TareResult
                ) -> None:
    for i, s in enumerate(specs):
        if s.limit is None or st.n[i] == 0 or not np.isfinite(target[i]):
            continue
        shift = target[i] - st.mean[i]
        if abs(shift) > s.limit:
            res.problems.append(f"{s.key} would shift by {shift:.4g}, more than {s.limit:.4g} "
                                f"(--max-offset-fs of full scale): {_SHIFT_CAUSES[s.kind]}")


def tare(cfg: RigConfig, specs: list[ChannelSpec], values: np.ndarray, *,
         alpha: np.ndarray | None = None, min_samples: int = DEFAULT_MIN_SAMPLES,
         false_alarm: float = FALSE_ALARM, status_counts: dict[str, int] | None = None,
         span_s: float = 0.0) -> TareResult:
    """Statistics, targets, new offsets and the refusal checks of one rest recording.

    ``values`` (N, C) calibrated with the current config (nan = missing); ``alpha`` the 14
    angles of S (default: the configured initial angles)."""
    values = np.asarray(values, float).reshape(-1, len(specs))
    st = _Stats.of(values)
    target = np.array([np.nan if s.target is None else s.target for s in specs])
    res = TareResult([], samples=int(values.shape[0]), span_s=float(span_s))
    alpha = cfg.identification.initial_angles_rad if alpha is None else np.asarray(alpha, float)
    _cell_targets(cfg, specs, st, alpha, target, res)
    new_offset = np.array([s.offset for s in specs], float)
    have = st.n > 0
    new_offset[have] += target[have] - st.mean[have]
    res.channels += [ChannelResult(s, int(st.n[i]), float(st.mean[i]), float(st.std[i]),
                                   float(st.max_abs[i]), float(target[i]),
                                   float(new_offset[i])) for i, s in enumerate(specs)]
    _few_samples(specs, st, min_samples, res)
    _rotor_turning(cfg, specs, st, res)
    _status_bits(status_counts or {}, res)
    _varying(specs, st, false_alarm, res)
    _big_shifts(specs, st, target, res)
    return res


def acquire(reader: Any, seconds: float, row: Callable[[Any], np.ndarray], n_channels: int,
            on_sample: Callable[[float], None] | None = None
            ) -> tuple[np.ndarray, float, Counter]:
    """Samples from a started reader for ``seconds`` of acquisition time (sample stamps):
    (values (N, C), time span, counts of status flags). Bounded: at most 1.5× the expected
    number of samples are kept."""
    from rsra.daq.bus.reader import HealthReport

    rate = reader.cfg.sample_rate_hz
    cap = int(math.ceil(seconds * rate * 1.5)) + 16
    values = np.full((cap, n_channels), np.nan)
    flags: Counter = Counter()
    k = 0
    t0 = t_last = None
    last_wall = time.monotonic()
    while k < cap:
        item = reader.get(timeout=0.1)
        now = time.monotonic()
        if item is None or isinstance(item, HealthReport):
            if now - last_wall > STALL_S:
                break  # nothing arrives: the caller reports too few samples
            continue
        last_wall = now
        if t0 is None:
            t0 = item.t
        if item.t - t0 >= seconds:
            break
        values[k] = row(item)
        for f in item.flags:
            if f.startswith(("overrange:", "fault:")):
                flags[f] += 1
        t_last = item.t
        k += 1
        if on_sample is not None:
            on_sample(item.t - t0)
    span = 0.0 if t0 is None or t_last is None else t_last - t0 + 1.0 / rate
    return values[:k], span, flags


def fragment(cfg: RigConfig, result: TareResult, *, angles_from: str, bus: str) -> str:
    """The ``[calibration]`` TOML fragment to adopt, commented."""
    tared = {c.spec.key for c in result.channels if c.n > 0}
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    omega = ("no rotor-speed node" if result.omega_max is None
             else f"|Ω| ≤ {result.omega_max:.3g} rad/s")
    lines = [
        f"# rsra zero: tare of rig {cfg.rig_name!r} ({cfg.source}), {stamp}",
        f"# samples: {result.samples} over {result.span_s:.3f} s of acquisition time on {bus}; "
        f"rotor stopped ({omega}), no applied load.",
        "#",
        "# Adopt it by replacing the [calibration] table of the rig config with this one.",
        "# value = gain * raw + offset: gains are kept from the config, offsets are new, so",
        "# that at rest every tared channel reads its target:",
        "#   accelerometers: the gravity vector in body axes, f = a - g = (0, 0, -g) =",
        f"#     (0, 0, {GRAVITY_AT_REST[2]:.5f}) m/s^2 (z down: -1000 mg). Assumes a level rig;",
        "#     gravity stays because the balance I = S T + R H (model 3) carries it on",
        "#     both sides.",
        "#   load cells: their dead-weight reactions, not 0: the smallest sigma-weighted",
        "#     correction with S(alpha) T = I at rest (static hub-load estimate = 0),",
        f"#     alpha = {angles_from}; the self-stress of the seven cells (the",
        "#     null space of S) stays as measured.",
        "#   rotor speed, reference balance, drive loads: 0.",
        "#   kept as configured: azimuth (its zero is the blade reference), channels of",
        "#     absent nodes.",
        "[calibration]",
    ]
    for c in result.channels:
        if c.n == 0:
            continue
        s = c.spec
        lines.append(f'"{s.key}" = {{ gain = {float(s.gain)!r}, offset = {float(c.new_offset)!r} }}'
                     f"  # mean {c.mean:.6g}, sigma {c.std:.4g}, n {c.n}, target {c.target:.6g}")
    for key, (gain, offset) in cfg.calibration.items():
        if key not in tared:
            lines.append(f'"{key}" = {{ gain = {float(gain)!r}, offset = {float(offset)!r} }}'
                         "  # kept")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# command line
