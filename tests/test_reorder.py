"""The reorder stage (daq.bus.reorder, docs/reliability.md "SYNC counter and frame times"):
the block interface equals the streaming one; a stream shuffled within the window comes out
as a stable sort; frames beyond it are late, never lost samples."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rsra.daq.bus.reorder import REORDER_WINDOW, FrameReorder, order


def _stream(ts, window):
    r = FrameReorder(window)
    out = [p for t in ts for p in r.push(t)]
    return out + r.flush()


def _blocks(ts, window, cuts):
    r = FrameReorder(window)
    idx, late = [], []
    bounds = sorted({0, len(ts), *[c % (len(ts) + 1) for c in cuts]})
    for a, b in zip(bounds[:-1], bounds[1:]):
        i, lt = r.push_block(np.asarray(ts[a:b], dtype=float))
        idx += i.tolist()
        late += lt.tolist()
    i, lt = r.flush_block()
    return list(zip(idx + i.tolist(), late + lt.tolist()))


times = st.lists(st.one_of(st.integers(0, 40).map(float), st.floats(0, 40, width=32)),
                 max_size=200)


@settings(max_examples=300, deadline=None)
@given(ts=times, window=st.integers(0, 12), cuts=st.lists(st.integers(0, 200), max_size=6),
       sort_first=st.booleans())
def test_block_interface_equals_streaming(ts, window, cuts, sort_first):
    if sort_first:  # the ordered fast path of push_block, too
        ts = sorted(ts)
    got = _blocks(ts, window, cuts)
    assert got == [(i, bool(lt)) for i, lt in _stream(ts, window)]
    perm, late = order(np.asarray(ts, dtype=float), window)
    assert [(int(i), bool(late[i])) for i in perm] == got
    assert sorted(perm.tolist()) == list(range(len(ts)))


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 300), window=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_a_stream_displaced_within_the_window_is_stably_sorted(n, window, seed):
    rng = np.random.default_rng(seed)
    # ties: stability matters; within DISCONTINUITY_S (a step back beyond it is not disorder)
    ts = np.sort(rng.integers(0, n // 2 + 1, n)) * 1e-3
    # displace every frame by at most `window` places: shuffle blocks of window + 1
    pos = np.arange(n)
    for a in range(0, n, window + 1):
        pos[a:a + window + 1] = rng.permutation(pos[a:a + window + 1])
    perm, late = order(ts[pos], window)
    assert not late.any()
    assert np.array_equal(pos[perm], pos[np.argsort(ts[pos], kind="stable")])


def test_frames_beyond_the_window_are_late_and_the_rest_in_order():
    ts = np.arange(100) * 1e-3  # (within DISCONTINUITY_S)
    ts = np.concatenate([ts[:10], ts[60:], ts[10:60]])  # 50 frames 40 places late
    perm, late = order(ts, window=8)
    assert late.sum() == 50  # the window had released frame 91 before frame 10 came
    kept = ts[perm][~late[perm]]
    assert np.all(np.diff(kept) >= 0)


def test_the_window_is_at_least_2000_frames():
    assert REORDER_WINDOW >= 2000


def test_time_going_back_further_than_a_second_is_released_not_sorted_in():
    """A recording joined to itself: the halves are not merged (the assembler counts the
    discontinuity), nothing is late."""
    half = np.arange(0, 1.5, 0.01)
    ts = np.concatenate([half, half])
    perm, late = order(ts, window=50)
    assert np.array_equal(perm, np.arange(len(ts))) and not late.any()


@settings(max_examples=200, deadline=None)
@given(ts=times, window=st.integers(0, 12))
def test_the_frame_generator_releases_what_the_block_interface_says(ts, window):
    from types import SimpleNamespace

    from rsra.daq.bus.reorder import reordered

    frames = [SimpleNamespace(timestamp=t, arbitration_id=0x80 if i % 3 == 0 else 0x181, i=i)
              for i, t in enumerate(ts)]
    r = FrameReorder(window)
    got = [m.i for m in reordered(frames, reorder=r, sync_id=0x80)]
    perm, late = order(np.asarray(ts, dtype=float), window)
    assert got == [int(i) for i in perm if not late[i]]
    assert r.late == int(late.sum())
    assert r.late_syncs == sum(1 for i in np.flatnonzero(late) if i % 3 == 0)
