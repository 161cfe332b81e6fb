"""`rsra demo` runs a few seconds in lock-step, exits 0 and prints its summary; --report writes
the plots."""
import json
import subprocess
import sys

from tests.helpers_net import free_tcp_port


def test_demo_runs_and_summarises(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    r = subprocess.run([sys.executable, "-m", "rsra", "demo", "--speed", "max", "--duration", "35",
                        "--zenoh-listen", ep, "--report", str(tmp_path / "rep"), "--json"],
                       capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "summary" in r.stdout
    # stdout is a pipe, not a terminal: no line wrapped at 80 columns (issue 13)
    lines = r.stdout.splitlines()
    assert any(x.startswith("rsra demo:") and f"telemetry on {ep} (try" in x for x in lines)
    # the accuracy by phase against the published σ, what each phase means (issue 28)
    rms = [x for x in lines if "RMS err/σ / beyond 3σ" in x]
    assert any(x.lstrip().startswith("H start") for x in rms), lines
    assert any(x.lstrip().startswith("H steady") for x in rms), lines
    assert all(len(x.split("3σ:")[-1].split()) == 12 for x in rms), rms
    assert any(x.lstrip().startswith("steady: calibrated steady state") for x in lines)
    # off a terminal: the view as a plain-text table, no box drawing (issue 28)
    assert any(x.lstrip().startswith("axis") and "steady err/sigma" in x for x in lines)
    assert not any(ch in r.stdout for ch in "┃│╭━")
    line = next(x for x in r.stdout.splitlines() if x.startswith('{"summary"'))
    summary = json.loads(line)["summary"]
    assert summary["samples"] == 7000 and summary["lost"] == 0
    assert summary["identification_runs"] >= 1
    pngs = list((tmp_path / "rep").glob("*.png"))
    assert len(pngs) >= 4 and all(p.stat().st_size > 10_000 for p in pngs)
    assert (tmp_path / "rep" / "summary.md").is_file()


def test_demo_summary_is_text_without_json(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    r = subprocess.run([sys.executable, "-m", "rsra", "demo", "--speed", "max", "--duration", "2",
                        "--zenoh-listen", ep], capture_output=True, text=True, timeout=300,
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "summary: samples 400" in r.stdout and '{"summary"' not in r.stdout


def test_demo_bad_argument_is_one_line_exit_2():
    r = subprocess.run([sys.executable, "-m", "rsra", "demo", "--scenario", "nosuch"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1


def test_a_console_on_a_pipe_or_file_wraps_nothing():
    import io

    from rich.table import Table

    from rsra.daq.cli.console import make_console

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


def _posterior_at(tmp_path, deg: float):
    """A saved posterior (through `rsra angles reset`) with every angle at `deg`."""
    from rsra.daq.cli import main
    from rsra.config.rig import default_config_path

    conf = tmp_path / "rig.toml"
    text = default_config_path().read_text(encoding="utf-8")
    assert text.count("initial_angles_deg = 0.0") == 1
    conf.write_text(text.replace("initial_angles_deg = 0.0", f"initial_angles_deg = {deg}"),
                    encoding="utf-8")
    post = tmp_path / "post.json"
    assert main(["angles", "reset", "--config", str(conf), str(post)]) == 0
    return post


def test_demo_flies_from_a_saved_posterior_with_identification_off(tmp_path):
    """Issue 14: `rsra demo --angles STATE --no-identification` — the angles of the posterior
    for the whole run, no identification run."""
    import math

    post = _posterior_at(tmp_path, 2.0)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    r = subprocess.run([sys.executable, "-m", "rsra", "demo", "--scenario", "flight", "--seed",
                        "7", "--speed", "max", "--duration", "6", "--angles", str(post),
                        "--no-identification", "--zenoh-listen", ep, "--json"],
                       capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL,
                       check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    line = next(x for x in r.stdout.splitlines() if x.startswith('{"summary"'))
    summary = json.loads(line)["summary"]
    assert summary["samples"] == 1200 and summary["identification_runs"] == 0
    assert summary["published"].get("angles", 0) == 0
    assert summary["alpha_applied"] == [math.radians(2.0)] * 14


def test_demo_refuses_a_bad_angles_file_in_one_line_before_starting(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    rep = tmp_path / "rep"
    r = subprocess.run([sys.executable, "-m", "rsra", "demo", "--angles", str(bad), "--report",
                        str(rep)], capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and str(bad) in r.stderr
    assert r.stdout == "" and not rep.exists()


def test_demo_phases_start_only_on_uncalibrated_angles(cfg):
    """The demo's accuracy by phase (issue 28): samples before the first accepted run are
    `start` when the run began on uncertain angles, `steady` when it began from a calibrated
    posterior (no angles_uncertain flag); σ is the record's published one."""
    from types import SimpleNamespace

    import numpy as np

    from rsra.daq.cli.demo_view import DemoState

    bound = np.full(6, 100.0)
    for first_flags, phase in ((["angles_uncertain"], "start"), ([], "steady")):
        st = DemoState(cfg, bound, cfg.rig_model().geometry.angle_names)
        truth = SimpleNamespace(H_true=np.zeros(6), alpha_true=np.zeros(14))
        for k in range(400):
            st.on_record("hub_loads", {"seq": k, "t": k * 0.005, "H": [50.0] * 6,
                                       "H_static": [0.0] * 6, "sigma_angles": [0.0] * 6,
                                       "flags": first_flags}, truth)
        bp = st.by_phase()["H"]
        assert bp[phase]["samples"] == 400 - 201  # scored after 1 s of settling
        np.testing.assert_allclose(bp[phase]["rms_over_sigma"], 0.5)
        assert [p for p, v in bp.items() if v] == [phase]
