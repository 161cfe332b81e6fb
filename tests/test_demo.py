"""`rsra demo` runs a few seconds in lock-step, exits 0 and prints its summary; --report writes
the plots."""
import json
import subprocess
import sys

from tests.helpers_net import free_tcp_port


def test_demo_runs_and_summarises(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    r = subprocess.run([sys.executable, "-m", "daq", "demo", "--speed", "max", "--duration", "6",
                        "--zenoh-listen", ep, "--report", str(tmp_path / "rep")],
                       capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "summary" in r.stdout
    line = next(x for x in r.stdout.splitlines() if x.startswith('{"summary"'))
    summary = json.loads(line)["summary"]
    assert summary["samples"] == 1200 and summary["lost"] == 0
    assert summary["identification_runs"] >= 1
    pngs = list((tmp_path / "rep").glob("*.png"))
    assert len(pngs) >= 4 and all(p.stat().st_size > 10_000 for p in pngs)
    assert (tmp_path / "rep" / "summary.md").is_file()


def test_demo_bad_argument_is_one_line_exit_2():
    r = subprocess.run([sys.executable, "-m", "daq", "demo", "--scenario", "nosuch"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
