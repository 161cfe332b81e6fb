"""P1 — PDO decode + sample assembly, frames/s on one core (docs/performance.md).

The frames are the simulator's own (``LockstepSim(cfg, autostart=True)``, the
ground-test aircraft: boot-ups, SYNC with counter, every TPDO, heartbeats), pre-queued on a
python-can virtual bus before the clock starts; one python-can Notifier thread then drains
the bus and the clock stops when the last sample has been assembled. Three contestants on
identical frames, interleaved round by round (best of the rounds):

* ours — ``daq.bus.reader.Reader`` (Listen, FrameClock: clock from the frames): FrameTap →
  per-COB-ID struct unpack → calibrated ``Sample`` objects into the reader's queue;
* the dispatch floor — canopen ``Network.subscribe`` with do-nothing callbacks on every
  COB-ID (canopen's MessageListener → ``Network.notify``): no decoding at all;
* canopen's PDO path — ``RemoteNode`` per node, ``tpdo.read(from_od=True)``, a callback per
  TPDO that reads every mapped variable's ``.raw`` (decoded values, no sample assembly).

Targets: ≥ 50 % of the floor, ≥ 2× canopen's PDO callbacks, ≥ 25× the 1 Mbit/s bus.
"""
from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable

import can
import canopen

from bench.common import arg_parser, interleaved, ratio, writer_from_args
from rsra.daq.bus.assembler import Sample
from rsra.config.rig import RigConfig, load_config
from rsra.daq.bus.reader import DropQueue, FrameClock, Listen, Reader
from rsra.sim_bus.bus_sim import FRAME_OVERHEAD_BITS
from rsra.sim_bus.drivers import LockstepSim

BENCH = "p1_decode"
DRAIN_TIMEOUT_S = 600.0
_chan = itertools.count()


def simulator_frames(cfg: RigConfig, n_samples: int, scenario: str = "ground-test",
                     seed: int = 1) -> tuple[list[can.Message], int]:
    """Every frame the lock-step simulator puts on the bus for ``n_samples`` SYNCs, in bus
    order, and the bit rate of its EDS (for the bus limit)."""
    chan = f"bench-p1-gen-{next(_chan)}"
    collect = can.Bus(interface="virtual", channel=chan, preserve_timestamps=True,
                      receive_own_messages=False)
    try:
        with LockstepSim(cfg, scenario, seed=seed, autostart=True, channel=chan,
                         keep_samples=False) as sim:
            bitrate = sim.bitrate
            for _ in range(n_samples):
                sim.step()
        frames = []
        while (m := collect.recv(0.0)) is not None:
            frames.append(m)
    finally:
        collect.shutdown()
    return frames, bitrate


def bus_limit_frames_per_s(frames: list[can.Message], bitrate: int) -> float:
    """Frames/s the bus carries at ``bitrate`` for this frame mix (no stuffing: the most
    frames the bus could carry, so the ratio against it is the conservative one)."""
    bits = sum(FRAME_OVERHEAD_BITS + 8 * len(m.data) for m in frames) / len(frames)
    return bitrate / bits


def _prequeued(frames: list[can.Message]) -> can.BusABC:
    """A receiving virtual bus with every frame already queued on it."""
    chan = f"bench-p1-{next(_chan)}"
    rx = can.Bus(interface="virtual", channel=chan, preserve_timestamps=True,
                 receive_own_messages=False)
    tx = can.Bus(interface="virtual", channel=chan, preserve_timestamps=True,
                 receive_own_messages=False)
    try:
        for m in frames:
            tx.send(m)
    finally:
        tx.shutdown()
    return rx


def _drain(network: canopen.Network, done: threading.Event, n_frames: int) -> float:
    """Start the Notifier on a pre-queued bus; frames/s until ``done``."""
    t0 = time.perf_counter()
    network.connect()
    try:
        if not done.wait(DRAIN_TIMEOUT_S):
            raise RuntimeError("the frames were not all processed")
        return n_frames / (time.perf_counter() - t0)
    finally:
        network.notifier.stop(2.0)
        network.notifier = None


def _last_tpdo(frames: list[can.Message], tpdo_cobs: set[int]) -> tuple[int, int]:
    """(COB-ID of the last TPDO on the bus, how many frames carry it): its final arrival
    is the end of the run for the peers."""
    last = next(m.arbitration_id for m in reversed(frames) if m.arbitration_id in tpdo_cobs)
    return last, sum(1 for m in frames if m.arbitration_id == last)


def _counter(target: int, done: threading.Event) -> Callable:
    n = [0]

    def cb(can_id: int, data: bytearray, timestamp: float) -> None:
        n[0] += 1
        if n[0] == target:
            done.set()
    return cb


def run_floor(frames: list[can.Message], last: tuple[int, int]) -> float:
    rx = _prequeued(frames)
    try:
        net = canopen.Network(rx)
        done = threading.Event()

        def nothing(can_id: int, data: bytearray, timestamp: float) -> None:
            pass
        for cob in {m.arbitration_id for m in frames}:
            net.subscribe(cob, _counter(last[1], done) if cob == last[0] else nothing)
        return _drain(net, done, len(frames))
    finally:
        rx.shutdown()


def run_canopen_pdo(cfg: RigConfig, frames: list[can.Message], last: tuple[int, int]) -> float:
    rx = _prequeued(frames)
    try:
        net = canopen.Network(rx)
        done = threading.Event()
        count = [0]
        present = {m.arbitration_id for m in frames}
        for nc in cfg.nodes:
            node = canopen.RemoteNode(nc.node_id, str(nc.eds))
            net.add_node(node)
            node.tpdo.read(from_od=True)
            for pdo in node.tpdo.map.values():
                if not pdo.enabled or pdo.cob_id not in present:
                    continue
                if pdo.cob_id == last[0]:
                    def cb(p: canopen.pdo.PdoMap) -> None:
                        for var in p:
                            _ = var.raw  # decode every mapped value
                        count[0] += 1
                        if count[0] == last[1]:
                            done.set()
                else:
                    def cb(p: canopen.pdo.PdoMap) -> None:
                        for var in p:
                            _ = var.raw  # decode every mapped value
                pdo.add_callback(cb)
                pdo.subscribe()
        return _drain(net, done, len(frames))
    finally:
        rx.shutdown()


class _TimedQueue(DropQueue):
    """The reader's queue, telling when the last sample has been assembled and queued."""

    def __init__(self, size: int, last_seq: int):
        super().__init__(size)
        self.last_seq = last_seq
        self.done = threading.Event()

    def put(self, item) -> None:
        super().put(item)
        if isinstance(item, Sample) and item.seq >= self.last_seq:
            self.done.set()


def run_ours(cfg: RigConfig, frames: list[can.Message], n_samples: int) -> tuple[float, dict]:
    rx = _prequeued(frames)
    items = _TimedQueue(n_samples + 1000, last_seq=n_samples - 1)
    r = Reader(cfg, rx, nodes=Listen(), clock=FrameClock(), items=items)
    try:
        t0 = time.perf_counter()
        r.start()  # Listen, FrameClock: the one Notifier thread, nothing else
        if not items.done.wait(DRAIN_TIMEOUT_S):
            raise RuntimeError(f"not every sample was assembled: {r.assembler.counters()}")
        rate = len(frames) / (time.perf_counter() - t0)
        counters = r.assembler.counters()
        if counters["complete"] != n_samples or items.dropped:
            raise RuntimeError(f"assembly went wrong: {counters}, dropped {items.dropped}")
        return rate, counters
    finally:
        r.close()
        rx.shutdown()


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
    n_samples, rounds = (200, 1) if args.tiny else (12000, 3)
    frames, bitrate = simulator_frames(cfg, n_samples)
    from rsra.daq.bus.decoder import DecodeTable
    last = _last_tpdo(frames, set(DecodeTable(cfg).tpdos))
    counters: dict = {}

    def ours() -> float:
        rate, c = run_ours(cfg, frames, n_samples)
        counters.update(c)
        return rate

    res = interleaved({"floor": lambda: run_floor(frames, last),
                       "canopen_pdo": lambda: run_canopen_pdo(cfg, frames, last),
                       "ours": ours}, rounds)
    best = {k: max(v) for k, v in res.items()}
    bus = bus_limit_frames_per_s(frames, bitrate)
    common = {"frames": len(frames), "samples": n_samples, "rounds": rounds,
                  "all_rounds": {k: [round(x) for x in v] for k, v in res.items()},
                  "samples_assembled": counters, "frames_per_sample": len(frames) / n_samples,
                  "scenario": "ground-test", "bus_bitrate": bitrate, "threads": "one Notifier thread"}
    r_floor = ratio(best["ours"], best["floor"])
    w.add("vs_dispatch_floor", best["ours"], "frames/s", peer="canopen Network.subscribe "
          "do-nothing callbacks (dispatch floor)", peer_figure=best["floor"],
          ratio_value=r_floor, ratio_is="figure/peer", target="≥ 0.5 × the dispatch floor",
          met=r_floor is not None and r_floor >= 0.5, **common)
    r_pdo = ratio(best["ours"], best["canopen_pdo"])
    w.add("vs_canopen_pdo", best["ours"], "frames/s", peer="canopen RemoteNode.tpdo callbacks",
          peer_figure=best["canopen_pdo"], ratio_value=r_pdo, ratio_is="figure/peer",
          target="≥ 2 × canopen's PDO callbacks", met=r_pdo is not None and r_pdo >= 2.0,
          **common)
    r_bus = ratio(best["ours"], bus)
    w.add("vs_bus", best["ours"], "frames/s", peer=f"{bitrate / 1e6:g} Mbit/s bus, this frame "
          "mix, no stuffing", peer_figure=bus, ratio_value=r_bus, ratio_is="figure/peer",
          target="≥ 25 × the 1 Mbit/s bus", met=r_bus is not None and r_bus >= 25.0, **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
