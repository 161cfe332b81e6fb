"""What the cross-process benchmarks share (P5c, P6a, P8, the stage profile): child
processes that die with the benchmark, the shared bus (``rsra bus``), a rig config at
another sample rate, a Zenoh subscriber that stamps arrivals, a process's CPU time, and the
floor of the shared-bus topology — a do-nothing master and a do-nothing responder exchanging
the same frames through the same transport (docs/performance.md).
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench.common import BLAS_ENV

CONNECT_TIMEOUT_S = 180.0  # the machine is shared: start-up can take a minute


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, proc: subprocess.Popen | None, timeout: float = CONNECT_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"the process exited ({proc.returncode}) before listening")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on port {port} after {timeout} s")


def _die_with_parent() -> None:  # Linux: a child dies with the benchmark
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def spawn(argv: list[str], *, env: dict | None = None, log=None,
          prefix: list[str] | None = None) -> subprocess.Popen:
    """A child process (``argv`` after the interpreter; ``prefix`` before it, e.g. ``chrt``),
    single-threaded BLAS, dies with us."""
    return subprocess.Popen([*(prefix or []), sys.executable, *argv], env={**os.environ, **BLAS_ENV, **(env or {})},
                            stdout=log or subprocess.DEVNULL, stderr=log or subprocess.DEVNULL,
                            preexec_fn=_die_with_parent if sys.platform == "linux" else None)


def stop(proc: subprocess.Popen | None, timeout: float = 20.0) -> int | None:
    """SIGINT (the commands' clean stop), then SIGTERM, then SIGKILL."""
    if proc is None:
        return None
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        proc.kill()
        proc.wait(5)
    return proc.returncode


def start_sim_and_service(channel: str, cfg_path: str | Path | None = None
                           ) -> tuple[subprocess.Popen, subprocess.Popen, str]:
    """``rsra sim`` (ground-test) and ``rsra run`` each in its own process on the shared bus
    ``channel``; (simulator, service, the service's Zenoh endpoint) once the service listens.
    On any failure both are stopped before the error goes on."""
    sim = spawn(["-m", "rsra", "sim", "--scenario", "ground-test", "--interface", "remote",
                 "--channel", channel])
    svc = None
    try:
        time.sleep(2.0)
        port = free_tcp_port()
        ep = f"tcp/127.0.0.1:{port}"
        config = [] if cfg_path is None else ["--config", str(cfg_path)]
        svc = spawn(["-m", "rsra", "run", *config, "--interface", "remote", "--channel", channel,
                     "--zenoh-listen", ep, "--log-level", "warning"])
        wait_listening(port, svc)
    except BaseException:
        stop(svc)
        stop(sim)
        raise
    return sim, svc, ep


def start_bus() -> tuple[subprocess.Popen, str]:
    """``rsra bus`` on a free loopback port; returns the process and the python-can channel."""
    port = free_tcp_port()
    proc = spawn(["-m", "rsra", "bus", "--port", str(port)])
    wait_listening(port, proc)
    return proc, f"ws://127.0.0.1:{port}/"


def rate_config(rate: float, folder: str | Path) -> Path:
    """The packaged rig at another ``rig.sample_rate_hz`` (a copy in ``folder``, EDS paths
    made absolute)."""
    from rsra.config.rig import default_config_path

    src = default_config_path()
    text = src.read_text(encoding="utf-8")
    text, n = re.subn(r"(?m)^sample_rate_hz\s*=\s*[0-9.eE+-]+", f"sample_rate_hz = {float(rate)!r}",
                      text, count=1)
    if n != 1:
        raise RuntimeError(f"{src}: no sample_rate_hz line to change")
    text = re.sub(r'(?m)^eds\s*=\s*"([^"/][^"]*)"',
                  lambda m: f'eds = "{(src.parent / m.group(1)).as_posix()}"', text)
    out = Path(folder) / f"rig-{rate:g}.toml"
    out.write_text(text, encoding="utf-8")
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (all its threads), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Receiver:
    """Zenoh subscriber on ``<prefix>/hub_loads`` and ``<prefix>/health``: arrival stamps
    (bounded), the last health record."""

    def __init__(self, endpoint: str, prefix: str, capacity: int) -> None:
        import zenoh

        from rsra.daq.runtime.telemetry import viewer_config

        self.stamps = np.zeros(capacity)
        self.seq = np.zeros(capacity, dtype=np.int64)
        self.t = np.zeros(capacity)
        self.bad = np.zeros(capacity, dtype=bool)  # flagged lost_before or missing:<node>
        self.size = 0
        self.capacity = capacity
        self.n = 0
        self.overflow = 0
        self.health: dict | None = None
        self._lock = threading.Lock()
        self.session = zenoh.open(viewer_config([endpoint]))
        self.subs = [self.session.declare_subscriber(f"{prefix}/hub_loads", self._on),
                     self.session.declare_subscriber(f"{prefix}/health", self._on_health)]

    def _on(self, sample) -> None:
        t = time.time()
        raw = sample.payload.to_bytes()
        rec = json.loads(raw)
        with self._lock:
            if self.n >= self.capacity:  # bounded
                self.overflow += 1
                return
            self.stamps[self.n] = t
            self.seq[self.n] = rec["seq"]
            self.t[self.n] = rec["t"]
            self.bad[self.n] = any(f == "lost_before" or f.startswith("missing:")
                                   for f in rec.get("flags") or ())
            self.size = len(raw)
            self.n += 1

    def _on_health(self, sample) -> None:
        try:
            self.health = json.loads(sample.payload.to_bytes())
        except ValueError:
            pass

    def last_seq(self) -> int:
        with self._lock:
            return int(self.seq[: self.n].max()) if self.n else -1

    def window(self, seq_after: int, seq_to: int) -> dict:
        """Samples seq_after < seq ≤ seq_to: expected, received, flagged (lost_before,
        missing:<node>)."""
        with self._lock:
            seq, bad = self.seq[: self.n].copy(), self.bad[: self.n].copy()
        sel = (seq > seq_after) & (seq <= seq_to)
        got = int(len(np.unique(seq[sel])))
        return {"expected": seq_to - seq_after, "received": got,
                "missing": seq_to - seq_after - got, "flagged": int(bad[sel].sum())}

    def count(self) -> int:
        with self._lock:
            return self.n

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()

    def series(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(seq, t, latency s) by seq."""
        with self._lock:
            seq, t, st = self.seq[: self.n].copy(), self.t[: self.n].copy(), self.stamps[: self.n].copy()
        o = np.argsort(seq, kind="stable")
        return seq[o], t[o], (st - t)[o]


def scored(seq: np.ndarray, t: np.ndarray, lat: np.ndarray, warmup: float, n_expected: int):
    """The samples of ``n_expected`` consecutive seq from ``warmup`` s after the first:
    (latencies s, received, missing)."""
    if len(seq) == 0:
        raise RuntimeError("the subscriber received nothing")
    k0 = int(np.searchsorted(t, t.min() + warmup))
    if k0 >= len(seq):
        raise RuntimeError(f"only {len(seq)} samples received, none after the warm-up")
    s0 = int(seq[k0])
    sel = (seq >= s0) & (seq < s0 + n_expected)
    got = int(len(np.unique(seq[sel])))
    return lat[sel], got, n_expected - got


# --------------------------------------------------------------- the floor: do-nothing peers
def response_frames(scenario: str = "ground-test") -> list[tuple[int, int]]:
    """(COB-ID, length) of every TPDO the simulated aircraft sends per SYNC in ``scenario``:
    the required nodes and the optional ones the scenario carries."""
    from rsra.config.rig import load_config
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.sim_bus.scenarios import load_scenario

    cfg = load_config()
    present = set(load_scenario(scenario).nodes_present)
    out = []
    for nl in DecodeTable(cfg).nodes:
        if nl.required or nl.name in present or nl.role in present:
            out += [(t.cob_id, t.length) for t in nl.tpdos]
    return out


def responder_main(channel: str, frames: list[tuple[int, int]], stop_after: float,
                   ready=None) -> None:
    """Do-nothing responder: on every SYNC (0x080) send the same frames, constant data.
    ``ready`` (an Event) is set once it is connected to the bus."""
    import can

    from rsra.canbus import shutdown_bus

    bus = can.Bus(channel=channel, interface="remote")
    if ready is not None:
        ready.set()
    msgs = [can.Message(arbitration_id=c, data=bytes(n), is_extended_id=False) for c, n in frames]
    end = time.monotonic() + stop_after
    try:
        while time.monotonic() < end:
            m = bus.recv(0.2)
            if m is not None and m.arbitration_id == 0x80:
                for r in msgs:
                    bus.send(r)
    finally:
        shutdown_bus(bus)


def floor_publisher(endpoint: str, key: str):
    """(session, publisher) of a do-nothing master: a Zenoh peer listening on ``endpoint``
    (loopback, scouting off), the publisher declared as the service declares its own."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    return session, session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.DROP,
        priority=zenoh.Priority.REAL_TIME, express=True)


def floor_master_main(channel: str, frames: list[tuple[int, int]], rate: float, duration: float,
                      endpoint: str | None, key: str, size: int, result_path: str) -> None:
    """Do-nothing master: SYNC every period from a thread (the service's re-phasing rule,
    daq.master.SyncProducer), a receive loop counting the answers per period, and — with
    ``endpoint`` — the sample published over Zenoh (``{"seq", "t": SYNC send time}`` padded
    to ``size`` bytes) when a period's last frame arrives. Writes {sent, late, complete,
    incomplete} to result_path (a period is complete when exactly its frames came before the
    next SYNC)."""
    import can

    from rsra.canbus import shutdown_bus

    bus = can.Bus(channel=channel, interface="remote")
    pub = session = None
    if endpoint:
        session, pub = floor_publisher(endpoint, key)
        deadline = time.monotonic() + 2.0  # the subscriber connects (at most 2 s)
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
    ids = {c for c, _ in frames}
    n_frames = len(frames)
    period = 1.0 / rate
    cap = int(rate * duration) + 1000
    counts = np.zeros(cap, dtype=np.int32)  # frames received per SYNC (bounded)
    st = {"sent": 0, "late": 0}
    cur = [-1, 0.0]  # the last SYNC's seq and send time (the producer writes, the loop reads)
    stop_ev = threading.Event()
    sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
    pad = "x" * max(0, size - 40)

    def producer() -> None:
        due = time.perf_counter()
        while not stop_ev.is_set() and st["sent"] < cap:
            cur[:] = [st["sent"], time.time()]
            bus.send(sync)
            st["sent"] += 1
            now = time.perf_counter()
            due += period
            if due < now + 0.5 * period:
                st["late"] += 1
                due = now + 0.5 * period
            stop_ev.wait(due - now)

    th = threading.Thread(target=producer, daemon=True)
    end = time.monotonic() + duration
    th.start()
    try:
        while time.monotonic() < end:
            m = bus.recv(0.1)
            if m is None or m.arbitration_id not in ids:
                continue
            seq, t_sync = cur
            if seq < 0:
                continue
            counts[seq] += 1
            if counts[seq] == n_frames and pub is not None:
                pub.put(json.dumps({"seq": seq, "t": t_sync, "pad": pad}))
    finally:
        stop_ev.set()
        th.join(2.0)
        shutdown_bus(bus)
        if pub is not None:
            pub.undeclare()
            session.close()
        n = max(0, st["sent"] - 1)  # the last period may still be answering
        st["complete"] = int((counts[:n] == n_frames).sum())
        st["incomplete"] = n - st["complete"]
        Path(result_path).write_text(json.dumps(st))
