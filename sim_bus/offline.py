"""The off-line API: the same physics as arrays, no bus (model.md §8), for Monte Carlo work.

`simulate()` runs `AircraftPhysics` block by block and returns a `SimRun`: every SimSample
field stacked over samples, with the channel values quantised exactly as the bus encodes them
(docs/bus.md §1): REAL32 forces, rotor speed, balance and drive loads; INTEGER16 accelerometer counts
of 1 mg, saturated at the sensor's full scale; UNSIGNED16 azimuth, 0…65535 ↔ 0…2π. So an
off-line run equals what a reader decodes from the simulator's frames. `ChannelCodec` is the
one encoder both use: the CAN nodes put `ChannelCodec.encode()` values into their TPDOs.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rsra.config.devices import MILLI_G
from rsra.config.rig import RigConfig

from .physics import BLOCK_SIZE, SAMPLE_FIELDS, AircraftPhysics, SimSample
from .scenarios import Scenario, load_scenario

# docs/bus.md §1: accelerometer TPDO x, y, z INTEGER16, 1 count = 1 mg (the device profile's
# scale, config.devices); azimuth "UNSIGNED16 (0…65535 ↔ 0…2π)". The EDS data types (0x0003
# INTEGER16, 0x0006 UNSIGNED16, 0x0008 REAL32) match (sim_bus.nodeset checks them).
ACCEL_M_S2_PER_COUNT = MILLI_G
INT16_MAX = 32767
AZIMUTH_COUNTS = 65536
CHANNEL_FIELDS = ("T", "cell_status", "accel", "omega", "azimuth", "H_balance", "drive")
TRUTH_FIELDS = ("H_true", "alpha_true", "T_true", "accel_true", "unmodelled", "I_true",
                "drive_true", "base_accel")


@dataclass(frozen=True)
class EncodedChannels:
    """Raw bus values of one sample (or stacked samples)."""

    force: np.ndarray  # (…, 7) float32, N
    status: np.ndarray  # (…, 7) uint8
    accel_counts: np.ndarray  # (…, K, 3) int16, 1 mg
    omega: np.ndarray  # (…) float32, rad/s
    azimuth_counts: np.ndarray  # (…) uint16
    balance: np.ndarray  # (…, 6) float32
    drive: np.ndarray  # (…, Q) float32


class ChannelCodec:
    """Encode channels as the bus carries them, and decode them as the reader does."""

    def __init__(self, cfg: RigConfig):
        # the sensor saturates at its full scale (and INTEGER16 at 32767 counts)
        self.accel_limit = np.array([min(round(a.full_scale_g * 1000.0), INT16_MAX)
                                     for a in cfg.accelerometers], dtype=float)

    def encode(self, T, cell_status, accel, omega, azimuth, H_balance, drive) -> EncodedChannels:
        lim = self.accel_limit[:, None]
        counts = np.clip(np.rint(np.asarray(accel, float) / ACCEL_M_S2_PER_COUNT), -lim, lim)
        az = np.mod(np.rint(np.asarray(azimuth, float) * (AZIMUTH_COUNTS / (2 * math.pi))),
                    AZIMUTH_COUNTS)
        return EncodedChannels(
            force=np.asarray(T, float).astype(np.float32),
            status=np.asarray(cell_status).astype(np.uint8),
            accel_counts=counts.astype(np.int16),
            omega=np.asarray(omega, float).astype(np.float32),
            azimuth_counts=az.astype(np.uint16),
            balance=np.asarray(H_balance, float).astype(np.float32),
            drive=np.asarray(drive, float).astype(np.float32),
        )

    @staticmethod
    def decode(enc: EncodedChannels) -> dict[str, np.ndarray]:
        """Engineering values (float64) as the reader decodes them."""
        return {
            "T": enc.force.astype(float), "cell_status": enc.status,
            "accel": enc.accel_counts.astype(float) * ACCEL_M_S2_PER_COUNT,
            "omega": enc.omega.astype(float),
            "azimuth": enc.azimuth_counts.astype(float) * (2 * math.pi / AZIMUTH_COUNTS),
            "H_balance": enc.balance.astype(float), "drive": enc.drive.astype(float),
        }

    def quantise(self, **channels: np.ndarray) -> dict[str, np.ndarray]:
        """Channel values after a round trip through the bus encoding."""
        return self.decode(self.encode(**{k: channels[k] for k in CHANNEL_FIELDS}))


def quantise_sample(sample: SimSample, codec: ChannelCodec | RigConfig) -> SimSample:
    """A copy of `sample` whose channels are what the bus delivers (truth unchanged)."""
    if not isinstance(codec, ChannelCodec):
        codec = ChannelCodec(codec)
    q: dict[str, Any] = codec.quantise(**{k: getattr(sample, k) for k in CHANNEL_FIELDS})
    q["omega"] = float(q["omega"])
    q["azimuth"] = float(q["azimuth"])
    return dataclasses.replace(sample, **q)


@dataclass
class SimRun:
    """A simulated run as arrays: SimSample fields stacked over N samples, channels quantised
    as on the bus, plus the raw counts of the integer channels."""

    index: np.ndarray  # (N,) int64
    t: np.ndarray  # (N,) s
    T: np.ndarray  # (N, 7) as decoded from REAL32
    cell_status: np.ndarray  # (N, 7) uint8
    accel: np.ndarray  # (N, K, 3) m/s^2 decoded from the 1 mg counts
    omega: np.ndarray  # (N,)
    azimuth: np.ndarray  # (N,)
    H_balance: np.ndarray  # (N, 6)
    drive: np.ndarray  # (N, Q)
    H_true: np.ndarray
    alpha_true: np.ndarray
    T_true: np.ndarray
    accel_true: np.ndarray
    unmodelled: np.ndarray
    I_true: np.ndarray
    drive_true: np.ndarray
    base_accel: np.ndarray
    accel_counts: np.ndarray  # (N, K, 3) int16
    azimuth_counts: np.ndarray  # (N,) uint16
    dt: float = 0.0
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.index)

    def sample(self, i: int) -> SimSample:
        vals: dict[str, Any] = {}  # SimSample's fields: arrays and numbers
        for name in SAMPLE_FIELDS:
            v = getattr(self, name)[i]
            vals[name] = v.copy() if isinstance(v, np.ndarray) else v.item()
        return SimSample(**vals)

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)}


def run_meta(cfg: RigConfig, physics: AircraftPhysics) -> dict:
    """Names, units and provenance of a run (stored in the truth file)."""
    sym = {0: ("theta", "psi"), 1: ("delta", "psi"), 2: ("delta", "theta")}  # by nominal axis
    angle_names = []
    for c in cfg.cells:
        for s in sym[int(np.argmax(np.abs(c.nominal_axis)))]:
            angle_names.append(f"{s}_{c.name}")
    sc = physics.scenario
    return {
        "scenario": sc.name, "scenario_source": sc.source, "variants": dict(sc.variants),
        "seed": physics.seed, "sample_rate_hz": cfg.sample_rate_hz, "dt": physics.dt,
        "substeps": physics.substeps, "rig": cfg.rig_name, "rig_source": cfg.source,
        "cell_names": [c.name for c in cfg.cells],
        "accelerometer_names": [a.name for a in cfg.accelerometers],
        "drive_names": [e.name for e in cfg.external_loads], "angle_names": angle_names,
        "hub_frame": "body", "units": "SI: N, N·m, m/s^2, rad, rad/s, s",
        "mode_frequencies_hz": [] if sc.quasi_static else physics.mode_frequencies_hz().tolist(),
    }


def stack_samples(samples: list[SimSample], codec: ChannelCodec, dt: float = 0.0,
                  meta: dict | None = None, quantised: bool = False) -> SimRun:
    """A SimRun from streamed samples (e.g. the CAN nodes' record of what they sent)."""
    arrs = {name: np.array([getattr(s, name) for s in samples]) for name in SAMPLE_FIELDS}
    return _as_run(arrs, codec, dt, meta or {}, already_quantised=quantised)


def _as_run(arrs: dict, codec: ChannelCodec, dt: float, meta: dict,
            already_quantised: bool = False) -> SimRun:
    enc = codec.encode(**{k: arrs[k] for k in CHANNEL_FIELDS})
    q = {} if already_quantised else codec.decode(enc)
    return SimRun(**{**arrs, **q}, accel_counts=enc.accel_counts,
                  azimuth_counts=enc.azimuth_counts, dt=dt, meta=meta)


def simulate(cfg: RigConfig, scenario: Scenario | str, seed: int | None = None,
             n_samples: int | None = None, duration_s: float | None = None,
             block_size: int = BLOCK_SIZE) -> SimRun:
    """Simulate `n_samples` (or `duration_s`, default the scenario's run_s) off-line."""
    if isinstance(scenario, str):
        scenario = load_scenario(scenario)
    phys = AircraftPhysics(cfg, scenario, seed=seed, block_size=block_size)
    if n_samples is None:
        n_samples = round((duration_s if duration_s is not None else scenario.run_s)
                              * cfg.sample_rate_hz)
    if n_samples <= 0:
        raise ValueError(f"n_samples must be positive, got {n_samples}")
    blocks = [phys.next_block() for _ in range(-(-n_samples // phys.block_size))]
    arrs = {name: np.concatenate([b[name] for b in blocks])[:n_samples] for name in SAMPLE_FIELDS}
    return _as_run(arrs, ChannelCodec(cfg), phys.dt, run_meta(cfg, phys))
