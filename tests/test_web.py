"""`rsra web` (issue 18): the Open MCT gateway — dictionary, limits, bounded history, telemetry
files, Host/Origin refusal, bounded browser queues, the command's bad input, and a real
headless Chromium against `rsra run --sim ground-test`. Nothing here asserts timing."""
from __future__ import annotations

import asyncio
import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom

pytest.importorskip("aiohttp", reason="aiohttp (the gateway's server) is not installed")

from rsra.daq.web import dictionary as D  # noqa: E402
from rsra.daq.web.history import History, HistoryFileError, TelemetryFile  # noqa: E402
from rsra.daq.web.server import (Client, Gateway, allowed_hosts, openmct_dir,  # noqa: E402
                            request_allowed)
from rsra.daq.runtime.telemetry import payload_guard  # noqa: E402
from tests.helpers_net import free_tcp_port  # noqa: E402

from tests.helpers_proc import (CHROMIUM, CHROMIUM_FLAGS, launch_chromium,  # noqa: E402
                                spawn as _spawn, stop as _stop)


@pytest.fixture(scope="module")
def dic(cfg):
    return D.build_dictionary(cfg)


def _hub(seq, t, H=None, S=None, flags=()):
    return {"seq": seq, "sync": 1, "t": t, "frame": "body",
            "H": H if H is not None else [1.0, 2.0, -80000.0, 4.0, 5.0, 6.0],
            "H_static": S if S is not None else [1.0, 2.0, -80000.0, 4.0, 5.0, 6.0],
            "omega": 19.4, "flags": list(flags)}


# -- dictionary ----------------------------------------------------------------------------
def test_dictionary_is_built_from_the_rig_config(cfg, dic):
    from rsra.estimator.noise_budget import noise_budget

    ids = dic.by_id
    for i, ax in enumerate(D.AXES):
        unit = "N" if i < 3 else "N·m"
        for kind in ("H", "static", "upper", "lower", "angles"):
            assert ids[f"hub.{kind}.{ax}"].unit == unit
    assert [m.id for m in dic.measurements if m.group == "Load cells"] == \
        [f"cell.{c.name}" for c in cfg.cells]
    assert all(ids[f"cell.{c.name}"].unit == "N" for c in cfg.cells)
    assert {f"accel.{a.name}.{x}" for a in cfg.accelerometers for x in "xyz"} <= set(ids)
    assert ids["hub.omega"].unit == "rad/s"
    angles = cfg.rig_model().geometry.angle_names
    assert len(angles) == 14
    for n in angles:
        m = ids[f"angle.{n}"]
        assert m.unit == "deg" and "sigma" in [e[0] for e in m.extra]
        # issue 29: shown to 0.1° while their σ is 0.05°: three decimals, used by the plugin
        assert m.as_json()["decimals"] == 3
    assert ids["hub.H.Z"].as_json()["decimals"] == 1
    plugin = (Path(D.__file__).parent / "web-static" / "rsra-plugin.js").read_text()
    assert "m.decimals" in plugin
    assert ids["nis"].limits["yellow"] == pytest.approx(list(D.NIS_YELLOW))
    assert {f"node.{n.name}" for n in cfg.nodes} <= set(ids)
    assert {"ident.verdict", "ident.determined", "health.bus.errors",
            "health.samples.lost"} <= set(ids)
    # the posterior's count, named as the log's calibration line names it (not the window's)
    assert ids["ident.determined"].name == "directions determined (posterior, of 14)"
    nb = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad).total
    assert dic.sigma_static == pytest.approx(list(nb))
    json.dumps(dic.as_json(), allow_nan=False)  # strict JSON for the browser


# -- limits --------------------------------------------------------------------------------
def test_limit_thresholds():
    assert D.Z_YELLOW == pytest.approx(3.2905, abs=1e-3)
    assert D.static_limit(D.Z_YELLOW * 0.999) is None
    assert D.static_limit(-D.Z_YELLOW * 1.001) == "yellow"
    assert D.static_limit(D.Z_RED * 1.001) == "red"
    lo, hi = D.NIS_YELLOW
    assert D.nis_limit(6.0) is None
    assert D.nis_limit(lo * 0.99) == "yellow" and D.nis_limit(hi * 1.01) == "yellow"
    assert D.nis_limit(D.NIS_RED_HIGH * 1.01) == "red"
    assert D.node_limit("operational") is None
    assert D.node_limit("pre-operational") == "yellow"
    assert D.node_limit("lost") == "red" and D.node_limit("missing", True) == "red"
    assert D.node_limit("missing", False) is None
    assert D.flags_limit([]) is None and D.flags_limit(["lost_before"]) == "yellow"
    assert D.flags_limit(["predict_only", "missing:cell_C"]) == "red"
    assert D.verdict_limit(True, None) is None
    assert D.verdict_limit(False, "not_identifiable") == "yellow"
    assert D.verdict_limit(False, "inconsistent") == "red"
    assert D.status_limit(0) is None and D.status_limit(1) == "red" and D.status_limit(2) == "red"


def test_limits_false_alarm_rate_monte_carlo(dic):
    """A consistent static estimate (H + N(0, σ)) and a consistent NIS (χ²₆) go yellow at the
    1e-3 rate: the count lies inside its binomial 1e-3 acceptance band."""
    rng = np.random.default_rng(18)
    n = 200_000
    lo, hi = binom.ppf(5e-4, n, D.FALSE_ALARM_YELLOW), binom.isf(5e-4, n, D.FALSE_ALARM_YELLOW)
    dev = rng.standard_normal(n)
    flagged = sum(D.static_limit(float(x)) is not None for x in dev)
    assert lo <= flagged <= hi, (flagged, lo, hi)
    nis = rng.chisquare(6, n)  # a consistent filter: χ² with 6 dof (telemetry.md)
    flagged = sum(D.nis_limit(float(x)) is not None for x in nis)
    assert lo <= flagged <= hi, (flagged, lo, hi)
    # and through points(): the deviation is measured in the axis' noise-budget σ
    sig = dic.sigma_static
    H = [0.0, 0.0, -8e4, 0.0, 0.0, 0.0]
    S = [h + 3.0 * s for h, s in zip(H, sig)]  # 3 σ: inside
    assert all("lim" not in d for i, d in D.points(dic, "hub_loads", _hub(0, 1.0, H, S))
               if i.startswith("hub.static."))
    S = [h + 3.6 * s for h, s in zip(H, sig)]  # 3.6 σ: yellow on every axis
    got = {i: d for i, d in D.points(dic, "hub_loads", _hub(0, 1.0, H, S))}
    assert all(got[f"hub.static.{ax}"]["lim"] == "yellow" for ax in D.AXES)
    assert got["hub.upper.Z"]["value"] == pytest.approx(H[2] + D.Z_YELLOW * sig[2])


def test_sigma_angles_points_turn_yellow_beyond_the_static_sigma(dic):
    """`sigma_angles` (the flag `angles_uncertain`): yellow on an axis where it exceeds the
    axis' noise-budget σ, no limit below it, no point when null. Break-checked: the limit
    against 3.29 σ leaves the 1.5 σ axis without its limit."""
    sig = dic.sigma_static
    hub = _hub(0, 1.0)
    hub["sigma_angles"] = [0.5 * s for s in sig]
    hub["sigma_angles"][5] = 1.5 * sig[5]
    got = dict(D.points(dic, "hub_loads", hub))
    assert got["hub.angles.N"]["lim"] == "yellow"
    assert got["hub.angles.N"]["value"] == pytest.approx(1.5 * sig[5])
    assert all("lim" not in got[f"hub.angles.{ax}"] for ax in D.AXES[:5])
    hub["sigma_angles"] = None
    assert not any(i.startswith("hub.angles.") for i, _ in D.points(dic, "hub_loads", hub))


def test_points_of_every_key(dic, cfg):
    pts = dict(D.points(dic, "hub_loads", _hub(3, 100.0, H=[None] * 6,
                                               flags=["missing:cell_C", "predict_only"])))
    assert "hub.H.Z" not in pts and "hub.upper.Z" not in pts  # null H: no point
    assert pts["hub.static.Z"]["value"] == -80000.0 and pts["hub.static.Z"]["ref"] is None
    assert pts["hub.flags"] == {"utc": 100000.0, "value": "missing:cell_C, predict_only",
                                "lim": "red"}
    cells = [c.name for c in cfg.cells]
    ch = {"seq": 3, "t": 100.0, "T": [1.0] * 6 + [None], "accel": [[0.1, 0.2, -9.81]],
          "status": dict(zip(cells, [0, 1, 2, 0, 0, 0]))}
    pts = dict(D.points(dic, "channels", ch))
    assert pts[f"cell.{cells[1]}"]["lim"] == "red" and "lim" not in pts[f"cell.{cells[0]}"]
    assert f"cell.{cells[6]}" not in pts
    assert pts[f"accel.{cfg.accelerometers[0].name}.z"]["value"] == -9.81
    assert dict(D.points(dic, "innovations", {"t": 1.0, "nis": 80.0}))["nis"]["lim"] == "red"
    names = list(dic.angles)
    P = (np.eye(14) * np.radians(0.1) ** 2).tolist()
    ang = {"t": 5.0, "names": names, "alpha": [np.radians(2.0)] * 14, "P": P,
           "accepted": False, "reason": "inconsistent", "detail": "gate", "determined": 14}
    pts = dict(D.points(dic, "angles", ang))
    a = pts[f"angle.{names[0]}"]
    assert a["value"] == pytest.approx(2.0) and a["sigma"] == pytest.approx(0.1)
    assert a["lo"] == pytest.approx(1.9) and a["hi"] == pytest.approx(2.1)
    assert pts["ident.verdict"]["value"] == "rejected: inconsistent"
    assert pts["ident.verdict"]["lim"] == "red" and pts["ident.determined"]["value"] == 14
    assert "ident.advice" not in pts  # known loads: no advice
    held = {**ang, "mode": "known_loads", "reason": "not_identifiable",
            "detail": "information_ratio"}  # a weak window, its information kept: not refused
    v = dict(D.points(dic, "angles", held))["ident.verdict"]
    assert v["value"] == "held" and "lim" not in v
    adv = {"determined": 2, "next": 0.74, "window": {"extra_s": 1.57, "gain": 1},
           "best": {"kind": "manoeuvre", "name": "Y", "gain": 1, "next": 1.41}}
    pts = dict(D.points(dic, "angles", {**ang, "advice": adv}))
    from rsra.estimator.flight_advice import advice_summary

    assert pts["ident.advice"]["value"] == advice_summary(adv)  # one sentence (issue 51)
    assert pts["ident.advice"]["value"].startswith("This window determines 2 directions.")
    health = {"t": 6.0, "nodes": {"cell_A": {"state": "lost", "required": True},
                                  "balance": {"state": "missing", "required": False}},
              "bus": {"errors": 2, "frames": 10}, "samples": {"lost": 0}}
    pts = dict(D.points(dic, "health", health))
    assert pts["node.cell_A"]["lim"] == "red" and "lim" not in pts["node.balance"]
    assert pts["health.bus.errors"]["lim"] == "yellow"
    assert "lim" not in pts["health.bus.frames"] and "lim" not in pts["health.samples.lost"]
    assert D.points(dic, "hub_loads", {"seq": 1}) == []  # no time: no point
    for _, d in D.points(dic, "hub_loads", _hub(1, 1.0)):
        json.dumps(d, allow_nan=False)


# -- history -------------------------------------------------------------------------------
def test_history_is_bounded_by_count_and_age(dic):
    h = History(10.0, {"hub_loads": 20.0})  # cap 250 messages
    assert h.cap("hub_loads") == 250
    t0 = 1000.0
    for i in range(400):  # 400 messages within 4 s: the count bound
        h.add("hub_loads", t0 + i * 0.01, json.dumps(_hub(i, t0 + i * 0.01)))
    assert h.count("hub_loads") == 250
    assert h.bytes == sum(len(x) for x in h._text["hub_loads"])
    for i in range(30):  # 1 Hz for 30 s: the age bound
        t = t0 + 10 + i
        h.add("hub_loads", t, json.dumps(_hub(1000 + i, t)))
    ts = list(h._t["hub_loads"])
    assert ts[-1] - ts[0] <= 10.0 and h.count("hub_loads") == 11
    assert h.bytes == sum(len(x) for x in h._text["hub_loads"])
    h.add("hub_loads", t0, json.dumps(_hub(0, t0)))  # out of order: a restarted service
    assert h.count("hub_loads") == 1


def test_history_query_is_strided_and_keeps_the_newest(dic):
    h = History(1000.0, {"hub_loads": 200.0})
    for i in range(1000):
        t = 50.0 + i * 0.005
        h.add("hub_loads", t, json.dumps(_hub(i, t, H=[float(i)] * 6)))
    got = h.query(dic, "hub.H.X", 50.0, 60.0, max_points=100)
    assert 90 <= len(got) <= 100
    assert got[-1]["value"] == 999.0  # the newest is in
    assert [d["utc"] for d in got] == sorted(d["utc"] for d in got)
    got = h.query(dic, "hub.H.X", 51.0, 51.1)
    assert [d["value"] for d in got] == [float(i) for i in range(200, 221)]
    assert h.query(dic, "no.such", 0, 1e12) == []


def test_telemetry_files_jsonl_and_mcap(dic, tmp_path):
    from rsra.daq.analysis.export import write_mcap

    recs = [("hub_loads", _hub(i, 10.0 + i * 0.005, H=[float(i)] * 6)) for i in range(50)]
    recs.append(("innovations", {"seq": 0, "t": 10.0, "nis": 5.0}))
    jl = tmp_path / "tel.jsonl"
    jl.write_text("".join(json.dumps({"key": k, **p}) + "\n" for k, p in recs))
    mc = tmp_path / "tel.mcap"
    with open(mc, "wb") as f:
        write_mcap(recs, f, dic.prefix)
    for path in (jl, mc):
        tf = TelemetryFile(path, dic.prefix)
        assert tf.counts == {"hub_loads": 50, "innovations": 1}
        assert (tf.t0, tf.t1) == (10.0, pytest.approx(10.245))
        got = tf.query(dic, "hub.H.Y", 0.0, 1e12)
        assert [d["value"] for d in got] == [float(i) for i in range(50)]
        assert len(tf.query(dic, "hub.H.Y", 0.0, 1e12, max_points=10)) <= 10
        assert tf.query(dic, "hub.H.Y", 20.0, 30.0) == []
        assert tf.query(dic, "nis", 0.0, 1e12)[0]["value"] == 5.0
    bad = tmp_path / "bad.jsonl"
    bad.write_text("not json\n")
    with pytest.raises(HistoryFileError, match="bad.jsonl:1"):
        TelemetryFile(bad, dic.prefix)
    with pytest.raises(HistoryFileError, match="no such file"):
        TelemetryFile(tmp_path / "nope.jsonl", dic.prefix)


# -- Host / Origin -------------------------------------------------------------------------
def test_request_allowed_host_and_origin():
    hosts = allowed_hosts("127.0.0.1", 8080)
    assert request_allowed({"Host": "127.0.0.1:8080"}, hosts) is None
    assert request_allowed({"Host": "localhost:8080",
                            "Origin": "http://localhost:8080"}, hosts) is None
    assert "Host" in request_allowed({"Host": "evil.example:8080"}, hosts)  # DNS rebinding
    assert "Host" in request_allowed({"Host": "127.0.0.1:9999"}, hosts)
    assert "Host" in request_allowed({}, hosts)
    assert "cross-origin" in request_allowed({"Host": "127.0.0.1:8080",
                                              "Origin": "http://evil.example"}, hosts)
    assert "cross-origin" in request_allowed({"Host": "127.0.0.1:8080",
                                              "Origin": "http://localhost:8080"}, hosts)
    assert "cross-origin" in request_allowed({"Host": "127.0.0.1:8080", "Origin": "null"},
                                             hosts)
    remote = allowed_hosts("192.0.2.7", 80, ["rig.example"])
    assert request_allowed({"Host": "rig.example"}, remote) is None
    assert request_allowed({"Host": "localhost:80"}, remote) is not None


def _gateway(dic, tmp_path, files=()):
    return Gateway(dic, History(60.0, {"hub_loads": 200.0}), list(files),
                   allowed_hosts("127.0.0.1", 0), guard=payload_guard(), openmct=tmp_path)


def test_http_and_websocket_refuse_other_hosts_and_origins(dic, tmp_path):
    from aiohttp import WSServerHandshakeError
    from aiohttp.test_utils import TestClient, TestServer

    (tmp_path / "openmct.js").write_text("// stand-in")

    async def go():
        gw = _gateway(dic, tmp_path)
        async with TestClient(TestServer(gw.app(), host="127.0.0.1")) as c:
            port = c.server.port
            gw.hosts = allowed_hosts("127.0.0.1", port)
            own = f"127.0.0.1:{port}"
            r = await c.get("/status", headers={"Host": own})
            assert r.status == 200 and (await r.json())["rig"] == dic.rig
            r = await c.get("/openmct/openmct.js", headers={"Host": own})
            assert r.status == 200
            r = await c.get("/api/dictionary", headers={"Host": f"evil.example:{port}"})
            assert r.status == 403
            r = await c.get("/api/history?id=hub.H.Z",
                            headers={"Host": own, "Origin": "http://evil.example"})
            assert r.status == 403
            with pytest.raises(WSServerHandshakeError) as e:
                await c.ws_connect("/ws", headers={"Host": own,
                                                   "Origin": "http://evil.example"})
            assert e.value.status == 403
            ws = await c.ws_connect("/ws", headers={"Host": own, "Origin": f"http://{own}"})
            await ws.send_str(json.dumps({"subscribe": ["hub.H.Z", "no.such"]}))
            for _ in range(100):
                if gw.clients and next(iter(gw.clients)).subs:
                    break
                await asyncio.sleep(0.01)
            assert next(iter(gw.clients)).subs == {"hub.H.Z"}
            gw.ingest("hub_loads", json.dumps(_hub(0, 1.0)))
            gw.flush()
            msg = json.loads((await ws.receive(timeout=10)).data)
            assert msg["points"] == [["hub.H.Z", {"utc": 1000.0, "value": -80000.0}]]
            await ws.close()
            gw.ingest("hub_loads", json.dumps(_hub(3, 1.1)))  # seq 1 and 2 missed
            st = gw.status()
            assert st["refused"] == 3 and st["points_sent"] == 1
            assert st["received"]["hub_loads"] == 2 and st["missed"]["hub_loads"] == 2

    asyncio.run(go())


# -- bounded browser queues ----------------------------------------------------------------
class _StalledWS:
    """A browser that never reads: every send waits forever."""

    def __init__(self):
        self.sends = 0

    async def send_str(self, text):
        self.sends += 1
        await asyncio.Event().wait()


def test_slow_browser_queue_is_bounded_and_drops_are_counted(dic):
    """A browser that stops reading: its queue stays at max_batches, the oldest batches are
    dropped and counted, and the gateway's ingest goes on (it never waits on a browser)."""

    async def go():
        gw = Gateway(dic, History(60.0, {"hub_loads": 200.0}), [], set(), guard=payload_guard())
        ws = _StalledWS()
        c = Client(ws, max_batches=5)
        c.subs = {f"hub.{k}.{ax}" for k in ("H", "static") for ax in D.AXES}
        gw.clients.add(c)
        writer = asyncio.create_task(c.writer())
        n_msgs, per_flush = 2000, 20  # 10 s at 200/s, flushed every 0.1 s
        for i in range(n_msgs):
            gw.ingest("hub_loads", json.dumps(_hub(i, 1.0 + i * 0.005)))
            if i % per_flush == per_flush - 1:
                gw.flush()
                await asyncio.sleep(0)
        offered = n_msgs * 12
        held = sum(len(b) for b in c.queue) + len(c.batch)
        in_flight = per_flush * 12 * ws.sends  # the one batch stuck in send_str
        assert len(c.queue) <= 5 and c.max_depth == 5
        assert c.dropped == offered - held - in_flight > 0
        assert gw.history.count("hub_loads") == n_msgs
        writer.cancel()
        return c.dropped, offered

    dropped, offered = asyncio.run(go())
    print(f"slow browser: {dropped} of {offered} points dropped (queue 5 batches)")


def test_batch_size_is_bounded(dic):
    c = Client(None, max_batches=2, max_batch_points=10)
    c.subs = {"hub.H.X"}
    c.offer([("hub.H.X", {"utc": i, "value": 0.0}) for i in range(25)])
    assert len(c.batch) == 10 and c.dropped == 15


# -- the command's bad input ---------------------------------------------------------------
def test_web_command_bad_input(tmp_path, capsys, monkeypatch):
    from rsra.daq import cli
    from rsra.daq.web import server

    monkeypatch.setattr(server, "OPENMCT_DIR", tmp_path / "none")
    assert cli.main(["web"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "make web" in err, err
    (tmp_path / "omct").mkdir()
    (tmp_path / "omct" / "openmct.js").write_text("//")
    monkeypatch.setattr(server, "OPENMCT_DIR", tmp_path / "omct")
    assert cli.main(["web", "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--allow-remote" in err, err
    bad = tmp_path / "x.jsonl"
    bad.write_text("{\n")
    assert cli.main(["web", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "x.jsonl:1" in err, err
    with pytest.raises(SystemExit) as e:
        cli.main(["web", "--port", "70000"])
    assert e.value.code == 2
    assert bad.read_text() == "{\n"


# -- a real browser ------------------------------------------------------------------------
def _browser_skip_reason() -> str | None:
    if not Path(CHROMIUM).is_file():
        return f"chromium is not installed ({CHROMIUM}; .ci/run installs Debian's chromium)"
    if openmct_dir() is None:
        return "the Open MCT files are not installed (run `make web`)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the Python package playwright is not installed (the test extra)"
    return None


@pytest.mark.timeout(300)
def test_browser_shows_hub_loads_live_and_history_after_reload(tmp_path):
    """Headless Chromium opens `rsra web` against `rsra run --sim ground-test` (real time):
    it finds the hub-load plot, sees new points arrive, and after a reload gets history."""
    why = _browser_skip_reason()
    if why:
        pytest.skip(why)
    from playwright.sync_api import sync_playwright

    zport, wport = free_tcp_port(), free_tcp_port()
    ep = f"tcp/127.0.0.1:{zport}"
    logs = {n: open(tmp_path / f"{n}.log", "w+") for n in ("run", "web")}
    procs: list[subprocess.Popen] = []
    try:
        run = _spawn(["run", "--sim", "ground-test", "--duration", "120", "--zenoh-listen", ep],
                     stdout=subprocess.DEVNULL, stderr=logs["run"])
        procs.append(run)
        web = _spawn(["web", "--port", str(wport), "--zenoh-connect", ep],
                     stdout=subprocess.PIPE, stderr=logs["web"])
        procs.append(web)
        line = web.stdout.readline()
        assert f"http://127.0.0.1:{wport}/" in line, line + _read(logs["web"])
        url = line.split("open ", 1)[1].split()[0]
        with sync_playwright() as pw:
            ctx = pw.chromium.launch_persistent_context(
                str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True,
                args=CHROMIUM_FLAGS, viewport={"width": 1600, "height": 1000})
            try:
                page = ctx.new_page()
                page.set_default_timeout(120_000)  # a loaded machine: no timing asserted
                errors = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url, timeout=120_000)
                plot = page.get_by_text("Hub loads (body axes)", exact=False).first
                plot.wait_for(timeout=120_000)
                page.locator(".gl-plot").first.wait_for(timeout=60_000)
                page.wait_for_function("() => (window.rsraStats.delivered['hub.H.Z'] || 0) > 0",
                                       timeout=120_000)
                n1 = page.evaluate("() => window.rsraStats.delivered['hub.H.Z']")
                page.wait_for_function(
                    f"() => window.rsraStats.delivered['hub.H.Z'] > {n1}", timeout=60_000)
                assert run.poll() is None, _read(logs["run"])
                page.reload()
                page.get_by_text("Hub loads (body axes)", exact=False).first.wait_for(
                    timeout=120_000)
                page.wait_for_function("() => (window.rsraStats.history['hub.H.Z'] || 0) > 0",
                                       timeout=120_000)
                assert not errors, errors
            finally:
                ctx.close()
    finally:
        for p in reversed(procs):
            _stop(p)
        if procs[-1:] and procs[-1].stdout:
            procs[-1].stdout.close()
    out = _read(logs["web"])
    assert "Traceback" not in out, out
    for f in logs.values():
        f.close()


def _read(f) -> str:
    f.flush()
    f.seek(0)
    return f.read()


# -- a gap breaks the line; the node table fits (issue 29) ---------------------------------
H_BLUE = (0x35, 0xC7, 0xFF)  # the filter estimate's colour in the hub-load plots


def _hub_run(t0: float, n: int, rate: float = 20.0, seq0: int = 0) -> list[dict]:
    """``n`` hub-load records from ``t0`` at ``rate``, X swinging ±5 kN (a visible line)."""
    return [_hub(seq0 + i, t0 + i / rate, H=[5000.0 * (-1) ** i, 0.0, -80000.0, 0.0, 0.0, 0.0])
            for i in range(n)]


def _blue_columns(png: bytes) -> np.ndarray:
    """Per pixel column of a plot screenshot: how many pixels have the filter's colour."""
    import io

    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    near = np.all(np.abs(a - np.array(H_BLUE)) < 40, axis=2)
    return near.sum(axis=0)


def _strip(cols: np.ndarray, lo: float, hi: float) -> int:
    n = len(cols)
    return int(cols[int(lo * n):int(hi * n)].sum())


_NODE_VALUE_VISIBLE = """() => {
  const td = Array.from(document.querySelectorAll('.c-lad-table td'))
    .find((d) => d.textContent.trim() === 'operational');
  if (!td) { return 'no node value shown'; }
  const r = td.getBoundingClientRect();
  const x = r.left + r.width / 2, y = r.top + r.height / 2;
  if (x > window.innerWidth || y > window.innerHeight) { return 'outside the window at ' + x; }
  const hit = document.elementFromPoint(x, y);
  return hit && (hit === td || td.contains(hit)) ? 'visible'
    : 'covered at x=' + Math.round(x) + ' by ' + (hit ? hit.className : 'nothing');
}"""


# every header of the angle table inside the table's box (a cut column: its right edge out)
_ANGLE_COLUMNS_VISIBLE = """() => {
  const t = Array.from(document.querySelectorAll('.c-telemetry-table'))
    .find((x) => x.querySelector('tbody td') !== null);
  if (!t) { return 'no angle table with rows'; }
  const box = t.getBoundingClientRect();
  const cut = Array.from(t.querySelectorAll('thead th'))
    .filter((th) => th.getBoundingClientRect().width > 0)
    .filter((th) => th.getBoundingClientRect().right > Math.min(box.right, window.innerWidth) + 1)
    .map((th) => th.textContent.trim() + ' cut by '
      + Math.round(th.getBoundingClientRect().right - box.right) + ' px');
  return cut.length ? cut.join(', ') : 'visible';
}"""


@pytest.mark.timeout(300)
def test_browser_breaks_the_line_at_a_gap_and_shows_the_node_values(cfg, tmp_path):
    """A 30-s gap (a restarted service) in history and live: the plot's line stops at the
    gap (no filter-coloured pixel in the middle of it, where the old straight line ran);
    and the node table's value column and every column of the angle table are on screen at
    1600 px (they were cut off: the angle table's +1σ by 37 px). Break-checked (issue 29):
    without the gap points in history, then in live points, the strip assertion fails (60 and
    25 filter-coloured pixels); with the former 60/40 layout and ∓1σ columns, the angle
    table's check does."""
    why = _browser_skip_reason()
    if why:
        pytest.skip(why)
    import time

    import zenoh
    from playwright.sync_api import sync_playwright

    from rsra.daq.runtime.telemetry import viewer_config

    prefix = cfg.telemetry.prefix
    now = time.time()
    t_hist = now - 3600.0  # history from a file: 10 s, a 30-s gap, 10 s
    recs = [("hub_loads", r) for r in _hub_run(t_hist, 200) + _hub_run(t_hist + 40, 200, seq0=0)]
    nodes = {n.name: {"state": "operational", "required": n.required} for n in cfg.nodes}
    recs += [("health", {"t": t_hist + s, "nodes": nodes}) for s in range(0, 50, 5)]
    names = list(cfg.rig_model().geometry.angle_names)
    recs.append(("angles", {"t": t_hist + 5, "names": names, "alpha": [0.0123] * 14,
                            "P": np.diag([np.radians(0.05) ** 2] * 14).tolist(),
                            "accepted": True, "reason": None, "determined": 14}))
    jl = tmp_path / "gap.jsonl"
    jl.write_text("".join(json.dumps({"key": k, **p}) + "\n" for k, p in recs))
    zport, wport = free_tcp_port(), free_tcp_port()
    ep = f"tcp/127.0.0.1:{zport}"
    log = open(tmp_path / "web.log", "w+")
    web = None
    with zenoh.open(viewer_config([], listen=[ep])) as z:
        try:
            web = _spawn(["web", "--port", str(wport), "--zenoh-connect", ep, str(jl)],
                         stdout=subprocess.PIPE, stderr=log)
            line = web.stdout.readline()
            assert f"http://127.0.0.1:{wport}/" in line, line + _read(log)
            url = line.split("open ", 1)[1].split()[0].rstrip("/")
            with sync_playwright() as pw:
                ctx = pw.chromium.launch_persistent_context(
                    str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True,
                    args=CHROMIUM_FLAGS, viewport={"width": 1600, "height": 1000})
                try:
                    page = ctx.new_page()
                    page.set_default_timeout(120_000)  # a loaded machine: no timing asserted
                    errors = []
                    page.on("pageerror", lambda e: errors.append(str(e)))
                    s, e = int(t_hist * 1000), int((t_hist + 50) * 1000)
                    page.goto(f"{url}/#/browse/rsra:root/rsra:layout?tc.mode=fixed"
                              f"&tc.startBound={s}&tc.endBound={e}&tc.timeSystem=utc")
                    page.wait_for_function(
                        "() => (window.rsraStats.history['hub.H.X'] || 0) >= 400")
                    assert page.evaluate("() => window.rsraStats.gaps['hub.H.X']") == 1
                    page.wait_for_function("() => document.querySelectorAll("
                                           "'.c-lad-table td').length > 0")
                    page.wait_for_timeout(1500)  # the plot draws (nothing timed)
                    area = page.locator(".gl-plot-chart-area").first
                    cols = _blue_columns(area.screenshot())
                    # data over 0-20 % and 80-100 % of the width, the gap between
                    assert _strip(cols, 0.03, 0.17) > 50 and _strip(cols, 0.83, 0.97) > 50
                    assert _strip(cols, 0.25, 0.75) == 0, "a line drawn across the gap"
                    page.screenshot(path=str(tmp_path / "history-gap.png"))
                    assert page.evaluate(_NODE_VALUE_VISIBLE) == "visible"
                    page.wait_for_function("() => document.querySelectorAll("
                                           "'.c-telemetry-table tbody td').length > 0")
                    assert page.evaluate(_ANGLE_COLUMNS_VISIBLE) == "visible"

                    # live: two runs of points 95 s apart in time, sent one after the other
                    page.goto(f"{url}/#/browse/rsra:root/rsra:layout?tc.mode=local"
                              "&tc.startDelta=120000&tc.endDelta=5000&tc.timeSystem=utc")
                    page.reload()
                    page.get_by_text("REAL-TIME", exact=False).first.wait_for()
                    page.locator(".gl-plot-chart-area").first.wait_for()
                    key = f"{prefix}/hub_loads"
                    t1 = time.time()
                    for r in _hub_run(t1 - 115, 200):
                        z.put(key, json.dumps(r))
                    page.wait_for_function(
                        "() => (window.rsraStats.delivered['hub.H.X'] || 0) >= 200")
                    for r in _hub_run(t1 - 20, 200, seq0=200):
                        z.put(key, json.dumps(r))
                    page.wait_for_function(
                        "() => (window.rsraStats.delivered['hub.H.X'] || 0) >= 400")
                    assert page.evaluate("() => window.rsraStats.liveGaps['hub.H.X']") == 1
                    page.wait_for_timeout(1500)
                    cols = _blue_columns(area.screenshot())
                    page.screenshot(path=str(tmp_path / "live-gap.png"))
                    # the window is the last 125 s: the gap spans about 12-84 % of it
                    assert _strip(cols, 0.0, 0.2) > 50 and _strip(cols, 0.7, 1.0) > 50
                    assert _strip(cols, 0.35, 0.55) == 0, "a line drawn across the gap"
                    assert not errors, errors
                finally:
                    ctx.close()
        finally:
            if web is not None:
                _stop(web)
                web.stdout.close()
    out = _read(log)
    log.close()
    assert "Traceback" not in out, out


# -- readable at 1600×1000 and 1280×800 (issue 51) -----------------------------------------
def test_the_band_lines_are_their_envelope_live_and_in_history(dic):
    """Over minutes the band lines enclose the estimate instead of merging with it: each
    band point given is the furthest out of its chunk of time (every sample's H ± 3.29 σ lies
    within the lines), one per chunk, the same live and in history; other series pass
    unchanged. Break-checked: keeping the first point of a chunk instead of the furthest out
    fails the first assertion."""
    rng = np.random.default_rng(51)
    t0 = 1_000.0
    recs = [_hub(i, t0 + i / 200.0, H=[5000.0 * math.sin(i / 5.0) + 300.0 * rng.standard_normal(),
                                      0.0, -8e4, 0.0, 0.0, 0.0]) for i in range(2000)]
    live, raw = D.BandEnvelope(), []
    got: list[tuple[str, dict]] = []
    for r in recs:
        pts = D.points(dic, "hub_loads", r)
        raw += pts
        got += live.reduce(pts)
    chunk = D.BAND_CHUNK_MS
    for pid, side in (("hub.upper.X", 1), ("hub.lower.X", -1)):
        mine = [d for i, d in raw if i == pid]
        by_chunk: dict[int, list[float]] = {}
        for d in mine:
            by_chunk.setdefault(math.floor(d["utc"] / chunk), []).append(d["value"])
        want = [(max if side > 0 else min)(v) for _, v in sorted(by_chunk.items())]
        hist = D.envelope(pid, mine)
        assert [d["value"] for d in hist] == want
        shown = [d["value"] for i, d in got if i == pid]
        assert shown == want[:-1]  # live: a chunk is given when the next starts
    assert [d for i, d in got if i == "hub.H.X"] == [d for i, d in raw if i == "hub.H.X"]
    assert D.envelope("hub.H.X", [{"utc": 1.0, "value": 2.0}]) == [{"utc": 1.0, "value": 2.0}]


def test_web_names_the_rig_publishing_and_takes_its_packaged_config(tmp_path):
    """`rsra web` without --config, with only the flight rig publishing, shows it: its prefix,
    its packaged config (the page's cells and angles) and its name in the page's words; with a
    --config of another rig it refuses in one line; --rig NAME of none publishing too.
    Break-checked: without the packaged config it returns the bench rig and fails."""
    import argparse

    import zenoh

    from rsra.config.rig import load_config
    from rsra.daq.cli.commands.web import _whose
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.telemetry import TelemetryPublisher, viewer_config, zenoh_config

    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    conf = viewer_config([ep])

    def args(**kw):
        return argparse.Namespace(**{"prefix": None, "rig": None, "config": None, **kw})

    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as rig:
        pub = TelemetryPublisher(rig, "rsra/flight", {"rig": {"name": "flight"}})
        try:
            for _ in range(50):
                got, prefix, source = _whose(args(), cfg, conf)
                if prefix == "rsra/flight":
                    break
            assert prefix == "rsra/flight" and got.rig_name == "flight"
            assert source.startswith("rig flight on rsra/flight — host ")
            with pytest.raises(UsageError, match="--config describes rig bench"):
                _whose(args(config=["default"]), cfg, conf)
            with pytest.raises(UsageError, match="--rig hover: no rig hover publishing"):
                _whose(args(rig="hover"), cfg, conf)
        finally:
            pub.close()


_LABEL_OVERLAPS = """() => {
  // the drawn text of every axis label and tick label of every plot (the union of its
  // text nodes' boxes: the elements are wider than their text), and the pairs that overlap
  const textBox = (e) => {
    const walk = document.createTreeWalker(e, NodeFilter.SHOW_TEXT);
    let box = null;
    for (let n = walk.nextNode(); n; n = walk.nextNode()) {
      if (!n.textContent.trim()) { continue; }
      const r = document.createRange();
      r.selectNodeContents(n);
      const b = r.getBoundingClientRect();
      box = box === null ? { left: b.left, top: b.top, right: b.right, bottom: b.bottom }
        : { left: Math.min(box.left, b.left), top: Math.min(box.top, b.top),
          right: Math.max(box.right, b.right), bottom: Math.max(box.bottom, b.bottom) };
    }
    // what an ancestor clips (overflow other than visible, per direction) is not drawn
    for (let a = e.parentElement; box !== null && a !== null; a = a.parentElement) {
      const cs = getComputedStyle(a), c = a.getBoundingClientRect();
      if (cs.overflowX !== 'visible') {
        box.left = Math.max(box.left, c.left); box.right = Math.min(box.right, c.right);
      }
      if (cs.overflowY !== 'visible') {
        box.top = Math.max(box.top, c.top); box.bottom = Math.min(box.bottom, c.bottom);
      }
    }
    return box;
  };
  const out = [];
  let n = 0;
  document.querySelectorAll('.gl-plot').forEach((plot) => {
    const bs = Array.from(plot.querySelectorAll('.gl-plot-tick, .gl-plot-label'))
      .filter((e) => getComputedStyle(e).visibility !== 'hidden')
      .map((e) => ({ t: e.textContent.trim(), r: textBox(e) }))
      .filter((b) => b.r !== null && b.r.right > b.r.left && b.r.bottom > b.r.top);
    n += bs.length;
    for (let i = 0; i < bs.length; i++) {
      for (let j = i + 1; j < bs.length; j++) {
        const a = bs[i].r, b = bs[j].r;
        const w = Math.min(a.right, b.right) - Math.max(a.left, b.left);
        const h = Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top);
        if (w > 0.5 && h > 0.5) {
          out.push(bs[i].t + ' / ' + bs[j].t + ' (' + w.toFixed(1) + '×' + h.toFixed(1) + ' px)');
        }
      }
    }
  });
  return { labels: n, overlaps: out };
}"""

# every row of the nodes-and-health table and of the angle table on screen, not scrolled
_PANELS_VISIBLE = """() => {
  const shown = (el) => {
    const r = el.getBoundingClientRect();
    if (r.height <= 0 || r.top < 0 || r.left < 0 || r.bottom > innerHeight + 0.5
        || r.right > innerWidth + 0.5) { return false; }
    for (let p = el.parentElement; p; p = p.parentElement) {
      if (!/(auto|scroll|hidden)/.test(getComputedStyle(p).overflowY)) { continue; }
      const q = p.getBoundingClientRect();
      if (r.top < q.top - 0.5 || r.bottom > q.bottom + 0.5) { return false; }
    }
    return true;
  };
  const out = [];
  const lad = Array.from(document.querySelectorAll('.c-lad-table'))
    .find((t) => t.textContent.includes('bus frames'));
  if (!lad) { out.push('no nodes-and-health table'); } else {
    const rows = Array.from(lad.querySelectorAll('tbody tr'));
    rows.filter((tr) => !shown(tr)).forEach((tr) => out.push('health row not on screen: '
      + tr.textContent.trim().slice(0, 40)));
    if (rows.length < 20) { out.push('only ' + rows.length + ' health rows'); }
  }
  const table = Array.from(document.querySelectorAll('.c-telemetry-table'))
    .find((t) => t.textContent.includes('delta_A'));
  if (!table) { out.push('no angle table'); } else {
    const rows = Array.from(table.querySelectorAll('tbody tr'))
      .filter((tr) => tr.textContent.trim() !== '');
    rows.filter((tr) => !shown(tr)).forEach((tr) => out.push('angle row not on screen: '
      + tr.textContent.trim().slice(0, 40)));
    if (rows.length !== 14) { out.push(rows.length + ' angle rows rendered, not 14'); }
  }
  return out;
}"""


def _run_for_layout(cfg, t0: float, seconds: float = 125.0) -> list[tuple[str, dict]]:
    """Two minutes of a ground test as records (50 samples/s: enough for every pixel): hub
    loads stepping between load conditions with a 1/rev swing and noise, the NIS at 10/s with
    spikes at the steps, health every second, one identification."""
    rng = np.random.default_rng(7)
    names = list(cfg.rig_model().geometry.angle_names)
    nodes = {n.name: {"state": "operational", "required": n.required} for n in cfg.nodes}
    recs: list[tuple[str, dict]] = []
    for i in range(int(seconds * 50)):
        t = t0 + i / 50.0
        step = 12000.0 * (int((t - t0) / 30.0) % 2)
        swing = 4000.0 * math.sin(2 * math.pi * 3.1 * (t - t0))
        H = [step + swing + 800.0 * rng.standard_normal(), swing, -8e4 + step,
             2 * step + swing, step, swing]
        recs.append(("hub_loads", _hub(i, t, H=H, S=[h + 900.0 * rng.standard_normal()
                                                      for h in H])))
        if i % 5 == 0:
            nis = float(rng.chisquare(6)) * (40.0 if i % 1500 < 10 else 1.0)
            recs.append(("innovations", {"seq": i, "t": t, "nis": nis, "e": [0.0] * 6}))
        if i % 50 == 0:
            recs.append(("health", {"t": t, "nodes": nodes, "bus": {"frames": 10 * i,
                                                                    "errors": 0},
                                    "samples": {"complete": i, "lost": 0}}))
    recs.append(("angles", {"t": t0 + seconds - 5, "names": names, "alpha": [0.0123] * 14,
                            "P": np.diag([np.radians(0.05) ** 2] * 14).tolist(),
                            "accepted": True, "reason": None, "determined": 14,
                            "mode": "known_loads", "content": "static"}))
    recs.sort(key=lambda kr: kr[1]["t"])
    return recs


@pytest.mark.timeout(300)
def test_browser_layout_is_readable_at_1600x1000_and_1280x800(cfg, tmp_path):
    """Two minutes of telemetry in the default layout: no axis label or tick number of any
    plot overlaps another (the drawn text, at 1600×1000 and 1280×800), and at 1600×1000 every
    row of the nodes-and-health table and all 14 angles are on screen without scrolling.
    Break-checked: without the y-axis labels' room (index.html's tick padding) the overlap
    assertion fails ("X kN / 0"); with the former two-column layout the panel assertion."""
    why = _browser_skip_reason()
    if why:
        pytest.skip(why)
    import time

    from playwright.sync_api import sync_playwright

    t0 = time.time() - 3600.0
    jl = tmp_path / "two-minutes.jsonl"
    jl.write_text("".join(json.dumps({"key": k, **p}) + "\n"
                          for k, p in _run_for_layout(cfg, t0)))
    wport = free_tcp_port()
    log = open(tmp_path / "web.log", "w+")
    web = _spawn(["web", "--port", str(wport), "--zenoh-connect",
                  f"tcp/127.0.0.1:{free_tcp_port()}", str(jl)],
                 stdout=subprocess.PIPE, stderr=log)
    try:
        line = web.stdout.readline()
        assert f"http://127.0.0.1:{wport}/" in line, line + _read(log)
        url = line.split("open ", 1)[1].split()[0].rstrip("/")
        s, e = int(t0 * 1000), int((t0 + 125) * 1000)
        with sync_playwright() as pw:
            for w, h in ((1600, 1000), (1280, 800)):
                ctx = launch_chromium(pw, tmp_path / f"profile-{w}", w, h)
                try:
                    page = ctx.new_page()
                    page.set_default_timeout(120_000)  # a loaded machine: no timing asserted
                    page.goto(f"{url}/#/browse/rsra:root/rsra:layout?hideTree=true"
                              f"&hideInspector=true&tc.mode=fixed&tc.startBound={s}"
                              f"&tc.endBound={e}&tc.timeSystem=utc")
                    page.wait_for_function(
                        "() => ['X', 'Y', 'Z', 'L', 'M', 'N', 'nis'].every((a) => "
                        "(window.rsraStats.history[a === 'nis' ? a : 'hub.H.' + a] || 0) > 0)")
                    page.wait_for_function("() => document.querySelectorAll("
                                           "'.c-telemetry-table tbody td').length >= 14")
                    page.wait_for_timeout(2000)  # the plots draw (nothing timed)
                    page.screenshot(path=str(tmp_path / f"layout-{w}.png"))
                    got = page.evaluate(_LABEL_OVERLAPS)
                    assert got["labels"] > 40, got  # the six hub plots' and the NIS' labels
                    assert got["overlaps"] == [], (w, got["overlaps"])
                    if w == 1600:
                        assert page.evaluate(_PANELS_VISIBLE) == []
                finally:
                    ctx.close()
    finally:
        _stop(web)
        web.stdout.close()
    out = _read(log)
    log.close()
    assert "Traceback" not in out, out
