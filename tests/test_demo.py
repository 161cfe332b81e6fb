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
    # stdout is a pipe, not a terminal: no line wrapped at 80 columns (issue 13)
    lines = r.stdout.splitlines()
    assert any(x.startswith("rsra demo:") and f"telemetry on {ep} (try" in x for x in lines)
    rms = [x for x in lines if "hub-load RMS error / static bound" in x]
    assert len(rms) == 2 and all(len(x.split("):")[-1].split()) == 6 for x in rms), rms
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


def test_a_console_on_a_pipe_or_file_wraps_nothing():
    import io

    from rich.table import Table

    from daq.console import make_console

    c = make_console(file=io.StringIO())
    assert not c.is_terminal
    text = "telemetry on tcp/127.0.0.1:7447 " + "x" * 150
    c.print(text)
    t = Table("name", "value")
    t.add_row("a" * 70, "b" * 70)
    c.print(t)
    out = c.file.getvalue().splitlines()
    assert out[0] == text
    assert any("a" * 70 in x and "b" * 70 in x for x in out)  # the table's row on one line
