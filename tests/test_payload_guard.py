"""Every Zenoh payload a viewer or the service receives is untrusted (docs/reliability.md
"Untrusted telemetry", docs/telemetry.md §1): the payload guard (daq/payload_guard.py) in front
of `rsra listen` (table and --json), `rsra web` (its ingest and the late joiner's replies) and
the service's `state/*` queryable. The probes that used to kill a viewer, a hypothesis fuzz
over payloads (random bytes, deep nesting, huge, wrong types, non-finite numbers, valid
records), in-process and lock-step; one end-to-end run through real Zenoh sessions on
tcp/127.0.0.1; and `rsra web` shedding a flood of history requests with 503. Nothing here
asserts timing; ``RSRA_FUZZ_EXAMPLES=N`` runs N fuzz examples instead of 200."""
from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import subprocess
import sys
import threading
import time

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rsra.daq.cli.commands.listen import Listener, render
from rsra.daq.payload_guard import MAX_BYTES, MAX_DEPTH, BadPayload, nesting_depth
from rsra.daq.runtime.schema import FIELDS, json_schema
from rsra.daq.runtime.telemetry import TelemetryPublisher, payload_guard, viewer_config
from rsra.daq.web import dictionary as D
from rsra.daq.web.history import History
from rsra.daq.web.server import Gateway, allowed_hosts
from tests.helpers_net import free_tcp_port

KEYS = tuple(FIELDS)
HUB = {"seq": 3, "sync": 1, "t": 100.0, "frame": "body", "H": [1.0, 2.0, -8e4, 4.0, 5.0, 6.0],
       "H_static": [1.0, 2.0, -8e4, 4.0, 5.0, 6.0], "omega": 19.4, "flags": []}
# the probes of "Why" 3: each killed `rsra listen` and/or `rsra web`
PROBES = {
    "not UTF-8": b"\xff\xfe",
    "nested 200000 deep": b"[" * 200_000,
    "H: must be array or null": b'{"H":{"X":Infinity}}',
    "H_static: must be array or null": json.dumps({**HUB, "H_static": "wrong"}).encode(),
    "flags: must be array or null": json.dumps({**HUB, "flags": 7}).encode(),
}


def strict_loads(line: str):
    """json.loads that refuses NaN and Infinity (what a strict parser in another language
    does)."""
    def refuse(c):
        raise ValueError(f"non-strict JSON: {c}")
    return json.loads(line, parse_constant=refuse)


@pytest.fixture(scope="module")
def dic(cfg):
    return D.build_dictionary(cfg)


def table_text(lis: Listener) -> str:
    from rich.console import Console

    con = Console(file=io.StringIO(), width=160, record=True)
    con.print(render(lis.stats, "rsra/bench", "si", 1e9, lis.notes()))
    return con.export_text()


def gateway(dic) -> Gateway:
    return Gateway(dic, History(60.0, {"hub_loads": 200.0}), [], allowed_hosts("127.0.0.1", 0),
                   guard=payload_guard())


# -- the guard -----------------------------------------------------------------------------
def test_the_guard_refuses_each_probe_with_its_reason():
    g = payload_guard()
    for why, data in PROBES.items():
        with pytest.raises(BadPayload, match=why.replace("(", r"\(")):
            g.check("hub_loads", data)
    g.check("hub_loads", json.dumps(HUB).encode())  # a valid record passes
    with pytest.raises(BadPayload, match=f"more than {MAX_BYTES}"):
        g.check("hub_loads", b" " * (MAX_BYTES + 1))
    with pytest.raises(BadPayload, match="not an object"):
        g.check("hub_loads", b"[1, 2]")
    with pytest.raises(BadPayload, match="not JSON"):
        g.check("angles", b'{"names": ["\\ud800"]}')  # a lone surrogate: not Unicode
    with pytest.raises(BadPayload, match=r"nodes\.a\.emcy\[0\]\.code"):
        g.check("health", b'{"nodes": {"a": {"emcy": [{"code": "x"}]}}}')


def test_a_zenoh_payload_over_the_limit_is_never_copied_out():
    class Huge:  # a 1-GiB zenoh.ZBytes: its size is known without a copy
        def __len__(self):
            return 1 << 30

        def to_bytes(self):
            raise AssertionError("copied out")

    with pytest.raises(BadPayload, match=f"{1 << 30} bytes, more than {MAX_BYTES}"):
        payload_guard().check("hub_loads", Huge())
    got = payload_guard().check("hub_loads", zenoh.ZBytes(json.dumps(HUB).encode()))
    assert got.payload == HUB


def test_non_finite_numbers_become_null_and_are_flagged():
    g = payload_guard()
    got = g.check("hub_loads", b'{"seq": 1, "H": [NaN, Infinity, -Infinity, 1e400, 2, 3]}')
    assert got.non_finite and got.payload["H"] == [None, None, None, None, 2, 3]
    assert not g.check("hub_loads", json.dumps(HUB).encode()).non_finite


def test_nesting_depth_is_counted_before_parsing_and_ignores_brackets_in_strings():
    assert nesting_depth(b'{"a": [[1], {"b": [2]}]}') == 4
    assert nesting_depth(b'{"a": "[[[[{{{{", "b": [1]}') == 2
    assert nesting_depth(b'{"a": "\\"[[[", "b": "x\\\\"}') == 1  # escaped quote, backslash
    assert nesting_depth(b"[" * 200_000) == 200_000
    # an unterminated string with escaped quotes: stripped in one pass, not one per quote
    assert nesting_depth(b'"' + b'\\"' * 400_000 + b"\\") == 0
    deep = b'{"a":' * (MAX_DEPTH + 1) + b"1" + b"}" * (MAX_DEPTH + 1)
    with pytest.raises(BadPayload, match="nested"):
        payload_guard().check("hub_loads", deep)


def test_counters_stay_bounded_under_a_spray_of_keys():
    g = payload_guard()
    for i in range(1000):
        g.receive(f"k{i}", b"\xff")
    assert g.bad_total == 1000 and len(g.bad) <= 65


def test_the_lines_a_viewer_prints_hold_no_control_characters():
    """A key or field name from a peer reaches stderr (listen --json, web) only printable."""
    g = payload_guard()
    g.receive("evil\x1b]0;x\x07/hub_loads", b'{"H": 1}')
    g.receive("hub_loads", b'{"nodes\\u001b[2J": 1, "H": 1}')
    assert g.bad_total == 2 and all("\x1b" not in line and "\x07" not in line
                                    for line in g.lines())


# -- rsra listen: the table and --json ---------------------------------------------------
def test_listen_table_survives_every_probe_and_counts_it():
    lis = Listener(payload_guard())
    lis.feed("hub_loads", json.dumps(HUB).encode(), 0.0)
    for i, data in enumerate(PROBES.values()):
        lis.feed("hub_loads", data, float(i))
    text = table_text(lis)
    assert "5 bad messages from hub_loads (last: flags: must be array or null)" in text
    assert lis.stats["hub_loads"].count == 1  # only the valid one reached the table
    assert "-80000.0" in text


def test_listen_json_survives_every_probe_and_prints_strict_json():
    out = io.StringIO()
    lis = Listener(payload_guard(), out)
    for data in PROBES.values():
        lis.feed("hub_loads", data, 0.0)
    lis.feed("hub_loads", b'{"seq": 4, "H": [NaN, Infinity, 1, 2, 3, 4]}', 0.0)
    lis.feed("hub_loads", json.dumps(HUB).encode(), 0.0)
    recs = [strict_loads(line) for line in out.getvalue().splitlines()]
    assert recs[0] == {"key": "hub_loads", "seq": 4, "H": [None, None, 1, 2, 3, 4],
                       "non_finite": True}
    assert recs[1] == {"key": "hub_loads", **HUB}
    assert lis.guard.bad_total == len(PROBES)
    assert "1 message from hub_loads with non-finite numbers (shown as null)" in lis.notes()


def test_the_table_shows_no_markup_or_control_characters_from_a_payload():
    """A string from a peer is text: rich markup is shown as written (a '[/]' once raised
    MarkupError) and terminal control sequences are replaced."""
    lis = Listener(payload_guard())
    lis.feed("hub_loads", json.dumps({**HUB, "frame": "[/][bold]x\x1b]0;pwned\x07",
                                      "flags": ["[red]evil[/red]", None]}).encode(), 0.0)
    lis.feed("[/]weird", b'{"a": 1}', 0.0)
    text = table_text(lis)
    assert "[/][bold]x?]0;pwned?" in text and "[red]evil[/red]" in text
    assert "\x1b" not in text and "\x07" not in text and "[/]weird" in text


def test_the_table_draws_valid_records_with_nulls_and_odd_lengths():
    """Valid under the schema (every value may be null, arrays of any length): drawn with
    dashes, never an exception."""
    lis = Listener(payload_guard())
    lis.feed("hub_loads", json.dumps({**HUB, "H": [1.0, None, 2.0], "H_static": [0.0] * 9,
                                      "sigma_angles": None, "flags": [None, "predict_only"],
                                      "frame": None}).encode(), 0.0)
    lis.feed("angles", json.dumps({"names": [None, "a"], "alpha": [None], "sigma_cr": None,
                                   "accepted": None, "advice": {"best": None},
                                   "explanation": None, "hint": "h"}).encode(), 0.0)
    lis.feed("health", json.dumps({"nodes": {"n": {"state": None, "heartbeat_age": None,
                                                   "emcy": None}},
                                   "bus": None, "sync": {"rate_hz": None}}).encode(), 0.0)
    assert lis.guard.bad_total == 0
    text = table_text(lis)
    assert "flags: predict_only" in text and "hint: h" in text


def test_the_table_is_bounded_under_a_spray_of_keys():
    from rsra.daq.cli.commands.listen import MAX_KEYS

    lis = Listener(payload_guard())
    for i in range(MAX_KEYS + 44):
        lis.feed(f"spray/{i}", b'{"a": 1}', 0.0)
    assert len(lis.stats) == MAX_KEYS and lis.other_keys == 44
    assert f"44 messages on more than {MAX_KEYS} keys (not shown)" in lis.notes()


# -- rsra web: ingest, status, history -------------------------------------------------------
def test_web_ingest_survives_every_probe_and_shows_the_count(dic):
    gw = gateway(dic)
    for data in PROBES.values():
        gw.ingest("hub_loads", data)
    gw.ingest("hub_loads", b'{"seq": 1, "t": 1.0, "H": [NaN, 1, 2, 3, 4, 5]}')
    gw.ingest("hub_loads", json.dumps({**HUB, "seq": 2, "t": 2.0}).encode())
    gw.ingest("no_such_key", b"\xff")  # not telemetry rsra publishes: ignored, not kept
    st = gw.status()
    json.dumps(st, allow_nan=False)
    assert st["bad_messages"] == len(PROBES) and st["guard"]["bad_by_key"] == {
        "hub_loads": len(PROBES)}
    assert st["guard"]["non_finite"] == {"hub_loads": 1} and st["ignored"] == 1
    assert st["received"] == {"hub_loads": 2} and gw.history.count() == 2
    got = gw.history.query(dic, "hub.H.Y", 0.0, 10.0)
    assert [d["value"] for d in got] == [1, 2.0]


def test_a_telemetry_file_nested_too_deep_is_one_line_not_a_recursion(tmp_path):
    from rsra.daq.web.history import HistoryFileError, TelemetryFile

    f = tmp_path / "deep.jsonl"
    f.write_text(json.dumps({"key": "hub_loads", **HUB}) + "\n" + "[" * 200_000 + "\n")
    with pytest.raises(HistoryFileError, match=r"deep.jsonl:2: not a JSON line"):
        TelemetryFile(f, "rsra/bench")


@contextlib.asynccontextmanager
async def _history_burst(dic, waiting: int, records: int, requests: int, ready):
    """A gateway holding ``records`` hub-load records, ``waiting`` places in its history
    waiting room, served on loopback, and ``requests`` history requests sent at once;
    yields (gateway, client, headers, the requests' tasks) once ``ready(gateway)``."""
    from aiohttp.test_utils import TestClient, TestServer

    gw = gateway(dic)
    gw.max_waiting["history"] = waiting
    for i in range(records):
        gw.ingest("hub_loads", json.dumps({**HUB, "seq": i, "t": 1.0 + i / 200}).encode())
    async with TestClient(TestServer(gw.app(), host="127.0.0.1")) as c:
        gw.hosts = allowed_hosts("127.0.0.1", c.server.port)
        h = {"Host": f"127.0.0.1:{c.server.port}"}
        tasks = [asyncio.create_task(c.get("/api/history?id=hub.H.Z", headers=h))
                 for _ in range(requests)]
        for _ in range(2000):
            if ready(gw):
                break
            await asyncio.sleep(0.01)
        yield gw, c, h, tasks


def test_web_answers_strict_json_when_a_valid_record_overflows(dic):
    """Valid numbers a point overflows to inf — an angle of 1e308 rad in degrees, a time of
    1e306 s in ms: the browser's WebSocket batch and the history answer carry null, and the
    browser's writer goes on (json.dumps(allow_nan=False) raised in it)."""
    from aiohttp.test_utils import TestClient, TestServer

    angle = f"angle.{next(iter(dic.angles))}"
    records = [("angles", angle, {"t": 3.0, "names": [angle[6:]], "alpha": [1e308]}),
               ("hub_loads", "hub.H.Z", {**HUB, "t": 1e306})]

    async def go():
        gw = gateway(dic)
        async with TestClient(TestServer(gw.app(), host="127.0.0.1")) as c:
            gw.hosts = allowed_hosts("127.0.0.1", c.server.port)
            own = f"127.0.0.1:{c.server.port}"
            ws = await c.ws_connect("/ws", headers={"Host": own, "Origin": f"http://{own}"})
            await ws.send_str(json.dumps({"subscribe": [angle, "hub.H.Z"]}))
            for _ in range(500):
                if gw.clients and next(iter(gw.clients)).subs:
                    break
                await asyncio.sleep(0.01)
            got = []
            for key, mid, rec in records:
                gw.ingest(key, json.dumps(rec).encode())
                gw.flush()
                (pid, d), = strict_loads((await ws.receive(timeout=10)).data)["points"]
                r = await c.get(f"/api/history?id={mid}", headers={"Host": own})
                assert pid == mid and r.status == 200
                got += [d, strict_loads(await r.text())[-1]]
            assert got[0]["value"] is None and got[1]["value"] is None  # degrees(1e308)
            assert got[2]["utc"] is None and got[3]["utc"] is None  # 1e306 s in ms
            await ws.close()

    asyncio.run(go())


def test_web_history_bytes_are_bounded_per_key(dic):
    """Valid records of 60 kB at 200/s: the key's bytes stop at its byte bound (not 15 000
    messages × 60 kB = 900 MB) before the count or the age bound takes any."""
    h = History(60.0, {"hub_loads": 200.0})
    cap = h.byte_cap("hub_loads")
    big = json.dumps({**HUB, "x": "y" * 60_000})
    n = cap // len(big) + 50
    assert n < h.cap("hub_loads")
    for i in range(n):
        h.add("hub_loads", i / 200, big)
    assert cap - len(big) < h.bytes <= cap and h.evicted >= 50


# -- the service's state queryable ------------------------------------------------------------
class FakeQuery:
    """A query as Zenoh hands it to the queryable's callback."""

    def __init__(self, key: str, payload: bytes | None, parameters: str = ""):
        self.key_expr = zenoh.KeyExpr(key)
        self.payload = None if payload is None else zenoh.ZBytes(payload)
        self.parameters = parameters
        self.replies: list[tuple[str, bytes]] = []
        self.dropped = False

    def reply(self, key, data, encoding=None):
        self.replies.append((str(key), bytes(data)))

    def drop(self):
        self.dropped = True


@pytest.fixture(scope="module")
def publisher():
    """The service's publisher on a session with no endpoint (no socket: in-process)."""
    with zenoh.open(viewer_config([])) as s:
        pub = TelemetryPublisher(s, "rsra/test", {"rig": {"name": "bench"}})
        pub.publish("health", {"t": 1.0, "nodes": {}})
        try:
            yield pub
        finally:
            pub.close()


def test_the_state_queryable_ignores_and_counts_what_a_query_carries(publisher):
    before = publisher.bad_queries
    for data in [*PROBES.values(), None]:
        q = FakeQuery("rsra/test/state/*", data, "x=1" if data is None else "")
        publisher._answer(q)
        assert q.dropped and sorted(k for k, _ in q.replies) == [
            "rsra/test/state/config", "rsra/test/state/health"]
        assert all(strict_loads(d.decode()) is not None for _, d in q.replies)
    assert publisher.bad_queries - before == len(PROBES) + 1
    q = FakeQuery("rsra/test/state/*", None)
    publisher._answer(q)
    assert publisher.bad_queries - before == len(PROBES) + 1  # a plain query is not bad


# -- the fuzz: every kind of payload into every receiver ------------------------------------
def _from_schema(s: dict) -> st.SearchStrategy:
    """Values valid under one of the declared schemas (json_schema): nulls included."""
    out = []
    types = s.get("type", "object")
    for t in [types] if isinstance(types, str) else types:
        if t == "null":
            out.append(st.none())
        elif t == "integer":
            out.append(st.integers(-2**63, 2**63 - 1))
        elif t == "number":
            out.append(st.floats(allow_nan=False, allow_infinity=False) | st.integers(-10, 10))
        elif t == "string":
            out.append(st.text(max_size=30))
        elif t == "boolean":
            out.append(st.booleans())
        elif t == "array":
            out.append(st.lists(_from_schema(s.get("items", {"type": ["null"]})), max_size=7))
        elif t == "object":
            out.append(_object(s))
    return st.one_of(out)


def _object(s: dict) -> st.SearchStrategy:
    """An object with a few of the declared properties (and of any other names where the
    schema takes them), each valid."""
    props = {k: _from_schema(v) for k, v in s.get("properties", {}).items()}
    extra = s.get("additionalProperties")

    @st.composite
    def build(draw):
        names = draw(st.lists(st.sampled_from(sorted(props)), max_size=6, unique=True)) \
            if props else []
        d = {n: draw(props[n]) for n in names}
        if isinstance(extra, dict):
            for n in draw(st.lists(st.text(min_size=1, max_size=8), max_size=2)):
                d.setdefault(n, draw(_from_schema(extra)))
        return d
    return build()


VALID = {k: _from_schema(json_schema(k)) for k in KEYS}
ANY_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=10)
                        | st.floats(), lambda c: st.lists(c, max_size=4)
                        | st.dictionaries(st.text(max_size=6), c, max_size=4), max_leaves=20)


@st.composite
def payloads(draw) -> tuple[str, bytes]:
    key = draw(st.sampled_from(KEYS + ("other",)))
    kind = draw(st.sampled_from(["bytes", "deep", "huge", "wrong", "non_finite", "valid"]))
    if kind == "bytes":
        return key, draw(st.binary(max_size=200))
    if kind == "deep":
        n = draw(st.integers(MAX_DEPTH - 2, 5000))
        opener, closer = draw(st.sampled_from([(b"[", b"]"), (b'{"a":', b"}")]))
        return key, opener * n + draw(st.sampled_from([b"", b"1" + closer * n]))
    valid = draw(VALID[key if key != "other" else "hub_loads"])
    if kind == "huge":
        return key, json.dumps({**valid, "pad": "x" * (MAX_BYTES + 1)}).encode()
    if kind == "wrong":  # one field (or the whole record) of any JSON type
        if draw(st.booleans()) or not FIELDS.get(key):
            return key, json.dumps(draw(ANY_JSON)).encode()
        field = draw(st.sampled_from([p.split(".")[0].removesuffix("[]")
                                      for p, _, _ in FIELDS[key]]))
        return key, json.dumps({**valid, field: draw(ANY_JSON)}).encode()
    if kind == "non_finite":
        field = draw(st.sampled_from(["H", "t", "omega", "nis", "alpha", "x"]))
        bad = draw(st.sampled_from([float("nan"), float("inf"), -float("inf")]))
        return key, json.dumps({**valid, field: draw(st.sampled_from([bad, [bad, 1.0]]))}).encode()
    return key, json.dumps(valid).encode()


@settings(max_examples=int(os.environ.get("RSRA_FUZZ_EXAMPLES", "200")), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(msgs=st.lists(payloads(), min_size=1, max_size=4))
def test_fuzz_no_payload_kills_a_receiver(msgs, dic, publisher):
    """listen's table (fed and drawn) and --json (every line strict JSON, one per message
    let through), web's ingest (status strict JSON, history answered) and the service's
    queryable: none raises; every message is either shown or counted."""
    table, out = Listener(payload_guard()), io.StringIO()
    lines = Listener(payload_guard(), out)
    gw = gateway(dic)
    for key, data in msgs:
        shown = table.stats[key].count if key in table.stats else 0
        table.feed(key, data, 1.0)
        if key in ("hub_loads", "angles", "health") and key in table.stats \
                and table.stats[key].count > shown:
            table_text(table)  # the table draws the latest of these three
        lines.feed(key, data, 1.0)
        gw.ingest(key, data)
        q = FakeQuery("rsra/test/state/*", data)
        publisher._answer(q)
        assert q.dropped and len(q.replies) == 2
    table_text(table)
    shown = sum(s.count for s in table.stats.values())
    assert shown + table.guard.bad_total + table.other_keys == len(msgs)
    recs = [strict_loads(line) for line in out.getvalue().splitlines()]
    assert len(recs) == len(msgs) - lines.guard.bad_total
    assert all(isinstance(r, dict) and isinstance(r["key"], str) for r in recs)
    json.dumps(gw.status(), allow_nan=False)
    for mid in ("hub.H.Z", "cell.A", "nis", "ident.verdict", "node.cell_A", "health.bus.errors"):
        if mid in dic.by_id:
            for d in gw.history.query(dic, mid, 0.0, float("inf")):
                json.dumps(d, allow_nan=False)


# -- end to end through Zenoh on loopback ------------------------------------------------------
def _listen(ep: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "rsra", "listen", "--prefix", "rsra/test", "--zenoh-connect", ep,
         "--count", "6", "--duration", "30", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _publish_until_done(procs, pub, th: threading.Thread) -> None:
    """The first probe then a valid record, again and again until every receiver has what
    it waits for (Zenoh's discovery makes the subscribers appear at some point)."""
    deadline = time.monotonic() + 25
    seq = 0
    while (any(p.poll() is None for p in procs) or th.is_alive()) \
            and time.monotonic() < deadline:
        pub.put(b"\xff\xfe")
        pub.put(json.dumps({**HUB, "seq": seq}).encode())
        seq += 1
        time.sleep(0.05)


def test_end_to_end_a_bad_payload_is_counted_by_listen_and_web(dic):
    """A peer puts b"\\xff\\xfe" then valid records on rsra/test/hub_loads over
    tcp/127.0.0.1, and answers the gateway's late-joiner query with 100 000 '[': `rsra
    listen --json`, `rsra listen` (table) and the web gateway's Zenoh loop go on, show the
    valid ones and count the bad ones."""
    from rsra.daq.web.server import serve

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(viewer_config([], listen=[ep])) as s:
        pub = s.declare_publisher("rsra/test/hub_loads")
        # a peer that answers the late joiner's state/* query with garbage
        liar = s.declare_queryable("rsra/test/state/*", lambda q: q.reply(
            "rsra/test/state/health", b"[" * 100_000))
        procs = [_listen(ep, "--json"), _listen(ep)]
        gw = Gateway(dic, History(60.0, {"hub_loads": 200.0}), [], set(),
                     guard=payload_guard())
        stop = asyncio.Event()
        web_err: list[BaseException] = []

        def web_thread():
            async def main():
                loop = asyncio.get_running_loop()

                async def stopper():
                    while gw.bad_messages < 3 or sum(gw.received.values()) < 3:
                        await asyncio.sleep(0.05)
                    stop.set()
                t = loop.create_task(stopper())
                await asyncio.wait_for(serve(gw, "127.0.0.1", 0, viewer_config([ep]),
                                             "rsra/test", stop=stop), 30)
                t.cancel()
            try:
                asyncio.run(main())
            except BaseException as e:  # reported below
                web_err.append(e)

        th = threading.Thread(target=web_thread)
        th.start()
        try:
            _publish_until_done(procs, pub, th)
        finally:
            stop.set()
            for p in procs:
                if p.poll() is None:
                    p.kill()
            th.join(30)
        (out, err), (tout, terr) = (p.communicate(timeout=10) for p in procs)
        assert procs[0].returncode == 0, err
        recs = [strict_loads(line) for line in out.splitlines()]
        assert recs and all(r["key"] == "hub_loads" and r["H"][2] == -8e4 for r in recs)
        assert f"{6 - len(recs)} bad message" in err and "(last: not UTF-8)" in err
        assert procs[1].returncode == 0, terr
        assert "bad message" in tout and "from hub_loads (last: not UTF-8)" in tout
        assert not web_err, web_err
        liar.undeclare()
        st = gw.status()
        assert st["guard"]["last_reason"] == {"hub_loads": "not UTF-8",
                                              "health": "nested 100000 deep, more than 32"}
        assert st["received"]["hub_loads"] >= 3


# -- rsra web sheds load ------------------------------------------------------------------------
def _hold_history(monkeypatch) -> threading.Event:
    """Every history answer held until the returned gate is set (lock-step)."""
    import rsra.daq.web.server as server

    gate = threading.Event()
    real = server.points_of

    def held(*a):
        gate.wait(20)
        return real(*a)

    monkeypatch.setattr(server, "points_of", held)
    return gate


def test_web_sheds_history_requests_beyond_its_bound_and_stays_responsive(dic, monkeypatch):
    """40 history requests at once while each answer is held (a gate in the parse, lock-step):
    4 are answered, 36 get 503 with Retry-After at once; /status answers meanwhile; once the
    gate opens, the 4 get 200 and the next history request gets 200."""

    gate = _hold_history(monkeypatch)

    async def go():
        # (the waiting room: the next test)
        async with _history_burst(dic, 0, 100, 40, lambda gw: gw.busy["history"] == 4
                                  and gw.shed["history"] == 36) as (gw, c, h, tasks):
            assert gw.busy["history"] == 4 and gw.shed["history"] == 36
            r = await c.get("/status", headers=h)
            assert r.status == 200 and (await r.json())["shed"]["history"] == 36
            gate.set()
            rs = await asyncio.gather(*tasks)
            codes = sorted(r.status for r in rs)
            assert codes == [200] * 4 + [503] * 36
            assert all(r.headers["Retry-After"] == "1" for r in rs if r.status == 503)
            r = await c.get("/api/history?id=hub.H.Z", headers=h)
            assert r.status == 200 and len(await r.json()) == 100
            assert gw.busy["history"] == 0

    try:
        asyncio.run(go())
    finally:
        gate.set()


def test_history_requests_beyond_the_running_ones_wait_in_a_bounded_room(dic, monkeypatch):
    """An Open MCT page asks for the history of every object it shows at once: beyond the
    requests being answered (4) up to MAX_HISTORY_WAITING wait for a place and are answered
    in turn; only past that room is a request shed (503, a JSON body, Retry-After)."""

    gate = _hold_history(monkeypatch)

    async def go():
        async with _history_burst(dic, 10, 20, 20, lambda gw: gw.busy["history"] == 4
                                  and gw.waiting["history"] == 10) as (gw, c, h, tasks):
            assert (gw.busy["history"], gw.waiting["history"]) == (4, 10)
            gate.set()
            rs = await asyncio.gather(*tasks)
            assert sorted(r.status for r in rs) == [200] * 14 + [503] * 6
            shed = [await r.json() for r in rs if r.status == 503]
            assert all(b["error"] == "busy" for b in shed)
            assert gw.busy["history"] == 0 and gw.waiting["history"] == 0

    asyncio.run(go())
