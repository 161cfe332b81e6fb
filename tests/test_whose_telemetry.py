"""Whose telemetry a viewer shows (issue 51): every service declares who it is
(`<prefix>/alive/<rig>/<host>/<pid>/<started>`); `rsra listen` finds the rigs publishing,
shows the only one (a flight rig on rsra/flight without --prefix), names it, refuses to guess
among several (listing them; --rig NAME picks), hears it stop, and lets its rates fall to 0;
a second service on one prefix refuses to start, so two processes never share a stream."""
from __future__ import annotations

import os
import time

import pytest
import zenoh

from rsra.config.rig import load_config
from rsra.daq.cli import main
from rsra.daq.cli.commands.listen import KeyStats, Whose
from rsra.daq.cli.options import UsageError
from rsra.daq.runtime.instances import choose, parse, this_instance
from rsra.daq.runtime.telemetry import TelemetryPublisher, viewer_config, zenoh_config
from tests.helpers_net import free_tcp_port


def _wait(cond, what: str, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, what
        time.sleep(0.05)


def test_an_instance_key_round_trips_and_the_choice_is_explicit():
    a = this_instance("rsra/flight", "flight rig*", now=0.0)
    assert a.rig == "flight_rig" and a.started == "19700101T000000Z"
    assert parse(a.key) == a and parse("rsra/bench/alive") is None
    b = this_instance("rsra/bench", "bench", now=0.0)
    assert choose([a]) == (a, None)
    assert choose([]) == (None, "no rig publishing")
    inst, why = choose([a, b])
    assert inst is None and "2 rigs publishing" in why and "--rig NAME" in why
    assert choose([a, b], rig="bench") == (b, None)
    assert choose([a, b], prefix="rsra/flight") == (a, None)
    inst, why = choose([a], rig="bench")
    assert inst is None and "no rig bench publishing" in why and "flight_rig" in why


def test_rates_fall_to_zero_when_messages_stop():
    st = KeyStats("hub_loads")
    for i in range(50):
        st.add({"seq": i}, 100.0 + i * 0.005)
    last = 100.0 + 49 * 0.005
    assert st.rate(last + 0.01) == pytest.approx(200.0)
    assert st.rate(last + 1.5) == 0.0


def test_listen_finds_names_and_follows_the_rig_publishing():
    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as rig, \
            zenoh.open(viewer_config([ep])) as viewer:
        pub = TelemetryPublisher(rig, "rsra/flight", {"rig": {"name": "flight"}})
        whose = Whose(viewer, "rsra/bench", None, None)
        try:
            _wait(lambda: (whose.discover(time.monotonic()), whose.instance)[1] is not None,
                  "the flight rig's token")
            assert whose.prefix == "rsra/flight"  # not the config's rsra/bench
            title = whose.title()
            assert title.startswith("rig flight on rsra/flight — host ")
            assert f"pid {os.getpid()}, since " in title
            assert "stopped" not in title
            pub.close()
            _wait(lambda: (whose.poll(time.monotonic()), whose.stopped)[1] is not None,
                  "the token's DELETE")
            assert "stopped at" in whose.title()
        finally:
            whose.close()
            pub.close()


def test_several_rigs_are_listed_not_guessed_and_rig_picks_one():
    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as rig, \
            zenoh.open(viewer_config([ep])) as viewer:
        pubs = [TelemetryPublisher(rig, "rsra/bench", {"rig": {"name": "bench"}}),
                TelemetryPublisher(rig, "rsra/flight", {"rig": {"name": "flight"}})]
        try:
            w = Whose(viewer, "rsra/bench", None, None)

            def listed() -> bool:
                try:
                    w.discover(time.monotonic())
                except UsageError as e:
                    assert "2 rigs publishing" in str(e) and "rig bench" in str(e)
                    assert "rig flight" in str(e) and "--rig NAME" in str(e)
                    return True
                return False

            _wait(listed, "both tokens")
            w2 = Whose(viewer, "rsra/bench", None, "flight")
            w2.discover(time.monotonic())
            assert w2.prefix == "rsra/flight" and w2.instance.rig == "flight"
            w2.close()
            w3 = Whose(viewer, "rsra/bench", None, "hover")
            w3.discover(time.monotonic())
            assert w3.prefix is None and "no rig hover publishing" in w3.title()
        finally:
            for p in pubs:
                p.close()


def test_a_second_service_on_one_prefix_refuses_to_start(capsys):
    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as rig:
        pub = TelemetryPublisher(rig, cfg.telemetry.prefix, {"rig": {"name": "bench"}})
        try:
            rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "1",
                       "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}",
                       "--zenoh-connect", ep])
        finally:
            pub.close()
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "telemetry.prefix" in err and "another rsra publishes there (rig bench" in err
    assert "\n" not in err and "Traceback" not in err
