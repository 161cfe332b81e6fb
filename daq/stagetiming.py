"""Optional internal timing of the service's own share of the latency (the SYNC →
hub_loads latency): the last frame of a sample received → ``hub_loads`` handed to Zenoh.

Off by default and then free: ``TIMER`` is None and the two call sites test one module
global. A benchmark switches it on for one process by setting ``RSRA_STAGE_TIMING`` to a
file path in that process's environment; the stamps (``time.perf_counter``) go into
preallocated arrays indexed by ``seq`` modulo the capacity (bounded), and are written once,
at exit, as an ``.npz`` file with one row per sample:

* ``seq``;
* ``sync`` — the sample's SYNC time (the acquisition clock: the wall clock, ``time.time``)
  on the ``perf_counter`` scale (shifted by the offset between the two clocks taken once at
  start), so ``frame - sync`` is SYNC → the sample's last frame processed (in the service's
  process: the simulator's answer and python-can's delivery of its frames);
* ``frame`` — the sample was completed by its last TPDO (the assembler, in the thread that
  received the frame), or passed on incomplete at the next SYNC;
* ``handed`` — ``hub_loads`` encoded and about to be put (the estimator thread);
* ``put`` — Zenoh's ``put`` returned;
* ``frame_cpu``, ``put_cpu`` — the stamping thread's CPU clock (``time.thread_time``) at
  ``frame`` and ``put``: live both are stamped by the bus thread (the hub loads are
  published there), so their difference is the CPU the hub path took, caches as they are
  at 200 samples/s (cold), against the wall time beside it.

Nothing here is read by the service itself: it never changes what is computed or published.
"""
from __future__ import annotations

import atexit
import math
import os
import time

import numpy as np

ENV = "RSRA_STAGE_TIMING"
CAPACITY = 1 << 17  # samples kept (≈ 11 min at 200 samples/s): bounded


class StageTimer:
    """Per-sample stamps in preallocated arrays (bounded, no allocation per sample)."""

    def __init__(self, path: str, capacity: int = CAPACITY) -> None:
        self.path = path
        self.capacity = capacity
        self.seq = np.full(capacity, -1, dtype=np.int64)
        self.frame = np.full(capacity, np.nan)
        self.handed = np.full(capacity, np.nan)
        self.put = np.full(capacity, np.nan)
        self.frame_cpu = np.full(capacity, np.nan)
        self.put_cpu = np.full(capacity, np.nan)
        self.sync = np.full(capacity, np.nan)
        self.n_max = -1
        self.clock = time.perf_counter
        self.cpu = time.thread_time
        self.offset = time.time() - time.perf_counter()  # wall clock -> perf_counter scale

    def frame_done(self, seq: int, sync_t: float = math.nan) -> None:
        i = seq % self.capacity
        self.seq[i] = seq
        self.sync[i] = sync_t - self.offset
        self.frame_cpu[i] = self.cpu()
        self.frame[i] = self.clock()
        self.handed[i] = self.put[i] = self.put_cpu[i] = np.nan
        if seq > self.n_max:
            self.n_max = seq

    def handed_on(self, seq: int) -> None:
        i = seq % self.capacity
        if self.seq[i] == seq:
            self.handed[i] = self.clock()

    def put_done(self, seq: int) -> None:
        i = seq % self.capacity
        if self.seq[i] == seq:
            self.put[i] = self.clock()
            self.put_cpu[i] = self.cpu()

    def write(self) -> None:
        ok = self.seq >= 0
        order = np.argsort(self.seq[ok])
        np.savez(self.path, seq=self.seq[ok][order], frame=self.frame[ok][order],
                 handed=self.handed[ok][order], put=self.put[ok][order],
                 frame_cpu=self.frame_cpu[ok][order], put_cpu=self.put_cpu[ok][order],
                 sync=self.sync[ok][order])


def _from_env() -> StageTimer | None:
    path = os.environ.get(ENV)
    if not path:
        return None
    timer = StageTimer(path)
    atexit.register(timer.write)
    return timer


TIMER: StageTimer | None = _from_env()
