"""`rsra listen`'s counts: missed messages only where a key is published regularly."""
from __future__ import annotations

import numpy as np

from rsra.daq.cli.commands.listen import KeyStats, render


def feed(key: str, seqs) -> KeyStats:
    st = KeyStats(key)
    for i, q in enumerate(seqs):
        st.add({"seq": int(q)}, float(i))
    return st


def test_a_healthy_run_misses_nothing_on_any_key():
    """Before: `missed 10989` for angles and 10268 for innovations on a healthy run."""
    n = 12_000
    assert feed("hub_loads", range(n)).missed == 0
    assert feed("channels", range(n)).missed == 0
    assert feed("innovations", range(3, n, 10)).missed == 0
    # a lost sample (seq gap) where an innovation was due: its record never existed
    assert feed("innovations", [0, 10, 20, 40, 50]).missed == 1
    assert feed("angles", range(999, n, 1000)).missed is None  # on events, never dropped
    h = KeyStats("health")
    h.add({"t": 1.0}, 0.0)
    assert h.missed is None


def test_messages_never_received_are_counted_exactly():
    rng = np.random.default_rng(3)
    for key, stride in (("hub_loads", 1), ("innovations", 10), ("rsra/bench/innovations", 7)):
        seqs = np.arange(5, 20_000, stride)
        keep = rng.random(len(seqs)) > 0.03
        keep[:2] = True  # two in a row: the stride is known from the start
        st = feed(key, seqs[keep])
        assert st.missed == int((~keep).sum()), key


def test_the_table_shows_a_dash_where_nothing_is_counted():
    from rich.console import Console

    stats = {"angles": feed("angles", [999, 1999]), "hub_loads": feed("hub_loads", [0, 1, 3])}
    con = Console(width=200, record=True)
    con.print(render(stats, "rsra/bench", "si", 2.0))
    text = con.export_text()
    row = next(line for line in text.splitlines() if "angles" in line)
    assert "—" in row
    row = next(line for line in text.splitlines() if "hub_loads" in line)
    assert " 1 " in row


def test_a_rejected_run_shows_why_and_the_hint():
    """`rsra listen` under the angles table: the record's explanation and hint (issue 28)."""
    from rich.console import Console

    st = KeyStats("angles")
    st.add({"seq": 999, "mode": "known_loads", "content": "static", "accepted": False,
            "reason": "stale_input", "detail": "missing_samples",
            "explanation": "20.0 % of the window's 1000 samples unusable (allowed 5.0 %): "
                           "accel_1 missing in 20.0 %",
            "hint": "accel_1 silent or dropping frames: check its power", "names": ["a"],
            "alpha": [0.0], "sigma_cr": [None], "determined": 0}, 0.0)
    con = Console(width=200, record=True)
    con.print(render({"angles": st}, "rsra/bench", "si", 1.0))
    text = con.export_text()
    assert "why: 20.0 % of the window's 1000 samples unusable" in text
    assert "hint: accel_1 silent or dropping frames" in text


def test_a_filter_error_run_shows_its_advice():
    """`rsra listen` under the angles table: what would determine the rest (issue 25 item 5);
    a record without advice (known loads, older recordings) shows no such line."""
    from rich.console import Console

    rec = {"seq": 999, "mode": "filter_error", "content": "vibration", "accepted": True,
           "reason": None, "names": ["a"], "alpha": [0.0], "sigma_cr": [0.001],
           "determined": 2,
           "advice": {"determined": 2, "next": 0.74, "window": {"extra_s": 1.57, "gain": 1},
                      "best": {"kind": "manoeuvre", "name": "Y", "gain": 1, "next": 1.41}}}
    for advice, shown in ((rec["advice"], True), (None, False)):
        st = KeyStats("angles")
        st.add({**rec, "advice": advice}, 0.0)
        con = Console(width=200, record=True)
        con.print(render({"angles": st}, "rsra/bench", "si", 1.0))
        text = con.export_text()
        line = "advice: This window determines 2 directions. About 1.6 s more"
        assert (line in " ".join(text.split())) is shown, text
        assert ("advice:" in text) is shown


def test_the_health_line_rounds_its_floats():
    """Issue 29: `latency p50 0.8273124694824219 ms`."""
    import re

    from rich.console import Console

    st = KeyStats("health")
    st.add({"t": 1.0, "nodes": {}, "bus": {"frames": 10}, "samples": {"complete": 3},
            "latency_ms": {"p50": 0.8273124694824219, "p99": 12.43917236328125},
            "sync": {"duplicate": 0, "bad_timestamp": 0, "rate_hz": 199.12345678}}, 0.0)
    con = Console(width=200, record=True)
    con.print(render({"health": st}, "rsra/bench", "si", 2.0))
    text = con.export_text()
    assert "p50 0.827 ms p99 12.4 ms" in text, text
    assert not re.search(r"\d\.\d{5,}", text), text


def test_a_run_that_cannot_keep_up_says_why_once(caplog):
    """Issue 51: on the shared bus the default rig's 200 samples/s exceed what
    python-can-remote carries; the service says so once, in words, with what to do."""
    import logging
    from types import SimpleNamespace

    from rsra.daq.runtime.run_report import RateLowNotice

    n = RateLowNotice()
    ok = SimpleNamespace(rate_low=False, rate_hz=200.0)
    low = SimpleNamespace(rate_low=True, rate_hz=104.6)
    with caplog.at_level(logging.WARNING, logger="rsra"):
        assert n.check(ok, "remote", 200.0) is None
        said = n.check(low, "remote", 200.0)
        assert n.check(low, "remote", 200.0) is None  # once
    assert said is not None and said.startswith("samples arrive at 105/s, below the rig's "
                                                 "sample_rate_hz 200")
    assert "python-can-remote" in said and "112 samples/s" in said and "socketcan" in said
    assert [r.getMessage() for r in caplog.records] == [said]
    other = RateLowNotice().check(low, "socketcan", 200.0)
    assert other is not None and "does not keep up" in other and "112" not in other
