"""The simulator's real-time fast paths (sim_bus.bus_sim) change nothing the bus carries:
the physics block computed ahead of its SYNC (half a period after the SYNC that ended the
previous block) and the immutable frame payloads give the frames of lock-step bit for bit."""
from __future__ import annotations

import can
import pytest
from test_sim_nodes import channel_name

from daq.config import load_config
from sim_bus.bus_sim import Simulator
from sim_bus.physics import AircraftPhysics
from sim_bus.scenarios import load_scenario

BLOCK = 5  # samples per physics block
RATE = 50.0  # samples/s: the block is computed 10 ms after a SYNC, 10 ms before the next one


def _physics(cfg, seed: int) -> AircraftPhysics:
    return AircraftPhysics(cfg, load_scenario("ground-test"), seed=seed, block_size=BLOCK)


def _sync_and_tpdos(frames) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in frames
            if m.arbitration_id == 0x80 or 0x180 <= m.arbitration_id < 0x580]


@pytest.mark.timeout(60)
def test_physics_computed_ahead_in_real_time_gives_the_lockstep_frames():
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    n = 40  # 0.8 s of real time, 8 block boundaries
    chan = channel_name("ls-ahead")
    with Simulator(cfg, physics=_physics(cfg, 11), seed=11, lockstep=True, autostart=True,
                   channel=chan) as sim:
        ref = []
        for _ in range(n):
            ref.extend(sim.step())
    assert sim.prefetched == 0  # lock-step never computes ahead
    ref = _sync_and_tpdos(ref)

    chan = channel_name("rt-ahead")
    rx = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        sim = Simulator(cfg, physics=_physics(cfg, 11), seed=11, autostart=True, channel=chan)
        with sim:
            assert sim.run(duration=n * cfg.sample_period_s) == n
        got = []
        while (m := rx.recv(0)) is not None:
            assert isinstance(m.data, bytearray)  # receivers get python-can's usual type
            got.append(m)
    finally:
        rx.shutdown()
    assert _sync_and_tpdos(got) == ref
    # the blocks after the first were computed ahead (a late ticker may miss one: then the
    # SYNC computes it, as before — the frames above are the same either way)
    assert 1 <= sim.prefetched <= n // BLOCK
