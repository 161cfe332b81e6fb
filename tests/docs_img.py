"""Regenerate docs/img/ (`make docs-img`): the report's plots of a short flight-rig run and the
browser view (`rsra web`) of a live run at 1600×1000 and 1280×800.

    python -m tests.docs_img [--out docs/img] [--only report|browser] [--flight-s 60] [--live-s 125]

Every process it starts (the services, the gateway, Chromium) is stopped before it returns,
and dies with it if it is killed. Loopback only: the service listens on 127.0.0.1 at a free
port, the gateway binds 127.0.0.1. The PNGs are reduced to a palette (a few hundred kB in all).
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.helpers_net import free_tcp_port
from tests.helpers_proc import launch_chromium, spawn, stop

VIEWPORTS = ((1600, 1000), (1280, 800))
REPORT_PNGS = ("hub_loads.png", "hub_load_errors.png", "angles.png", "innovations.png")
REPORT_WIDTH = 900  # px: the report's plots, scaled down (the docs show them at about that)
REPORT_COLOURS = 32
SCREEN_COLOURS = 48  # Open MCT's dark theme


def shrink(src: Path, dst: Path, width: int | None = None, colours: int = SCREEN_COLOURS) -> None:
    """``src`` as a palette PNG of ``colours`` at ``dst`` (scaled to ``width`` px when
    given): a few hundred kB for all the images."""
    from PIL import Image

    with Image.open(src) as im:
        img = im.convert("RGB")
        if width is not None and img.width > width:
            img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
        img.quantize(colors=colours, method=Image.Quantize.MEDIANCUT).save(
            dst, optimize=True)


def _run(args: list[str], log: Path) -> None:
    with open(log, "w") as f:
        p = spawn(args, stdout=f, stderr=subprocess.STDOUT)
        try:
            rc = p.wait(timeout=1800)
        finally:
            stop(p)
    if rc != 0:
        raise SystemExit(f"docs_img: rsra {' '.join(args)} exited {rc}; see {log}")


def report_images(out: Path, work: Path, flight_s: float) -> list[Path]:
    """A flight-rig run at full speed, recorded, replayed and reported: its plots."""
    rec = work / "flight"
    _run(["run", "--config", "flight", "--sim", "flight", "--speed", "max", "--duration",
          str(flight_s), "--record", str(rec)], work / "run.log")
    _run(["replay", str(rec), "--config", "flight", "--out", str(work / "flight.jsonl")],
         work / "replay.log")
    _run(["report", str(work / "flight.jsonl"), "--config", "flight", "--truth",
          str(rec / "truth.npz"), "--out", str(work / "report")], work / "report.log")
    made = []
    for name in REPORT_PNGS:
        dst = out / f"report-{name}"
        shrink(work / "report" / name, dst, REPORT_WIDTH, REPORT_COLOURS)
        made.append(dst)
    return made


def _wait_for(log: Path, text: str, proc: subprocess.Popen, timeout: float = 300.0) -> None:
    """Until ``text`` is in the file ``log`` (what ``proc`` writes)."""
    end = time.monotonic() + timeout
    while text not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > end:
            raise SystemExit(f"docs_img: no {text!r} in {log}")
        time.sleep(0.5)


def browser_images(out: Path, work: Path, live_s: float) -> list[Path]:
    """`rsra run --sim ground-test` live, `rsra web` against it, Chromium at each viewport
    after ``live_s`` seconds (the real-time window is two minutes)."""
    from playwright.sync_api import sync_playwright

    zport, wport = free_tcp_port(), free_tcp_port()
    ep = f"tcp/127.0.0.1:{zport}"
    procs: list[subprocess.Popen] = []
    made = []
    with open(work / "live-run.log", "w") as rlog, open(work / "web.log", "w") as wlog:
        try:
            procs.append(spawn(["run", "--sim", "ground-test", "--duration",
                                str(live_s + 300), "--zenoh-listen", ep],
                               stdout=subprocess.DEVNULL, stderr=rlog))
            _wait_for(work / "live-run.log", "service started", procs[0])  # so the page
            # names it: rsra web picks the rig publishing when it starts
            web = spawn(["web", "--port", str(wport), "--zenoh-connect", ep],
                        stdout=subprocess.PIPE, stderr=wlog)
            procs.append(web)
            assert web.stdout is not None
            line = web.stdout.readline()
            if "open http" not in line:
                raise SystemExit(f"docs_img: rsra web did not start; see {work / 'web.log'}")
            url = line.split("open ", 1)[1].split()[0]
            time.sleep(live_s)
            with sync_playwright() as pw:
                for w, h in VIEWPORTS:
                    ctx = launch_chromium(pw, work / f"profile-{w}", w, h)
                    try:
                        page = ctx.new_page()
                        page.set_default_timeout(120_000)
                        page.goto(url, timeout=120_000)
                        page.locator(".gl-plot").first.wait_for()
                        page.wait_for_function(
                            "() => ['X', 'Y', 'Z', 'L', 'M', 'N'].every((a) => "
                            "(window.rsraStats.history['hub.H.' + a] || 0) > 0)")
                        page.wait_for_function("() => document.querySelectorAll("
                                               "'.c-telemetry-table tbody td').length > 0")
                        page.wait_for_timeout(3000)  # the plots draw
                        raw = work / f"openmct-{w}x{h}.png"
                        page.screenshot(path=str(raw))
                        dst = out / raw.name
                        shrink(raw, dst)
                        made.append(dst)
                    finally:
                        ctx.close()
        finally:
            for p in reversed(procs):
                stop(p)
            if procs[-1:] and procs[-1].stdout:
                procs[-1].stdout.close()
    return made


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.docs_img", description=__doc__)
    ap.add_argument("--out", default="docs/img", help="folder for the PNGs (default docs/img)")
    ap.add_argument("--only", choices=("report", "browser"), default=None)
    ap.add_argument("--flight-s", type=float, default=60.0,
                    help="seconds of the flight-rig run (acquisition time, default 60)")
    ap.add_argument("--live-s", type=float, default=125.0,
                    help="seconds of live telemetry before the screenshots (default 125)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (its path printed)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="rsra-docs-img-"))
    try:
        made = []
        if a.only in (None, "report"):
            made += report_images(out, work, a.flight_s)
        if a.only in (None, "browser"):
            made += browser_images(out, work, a.live_s)
    finally:
        if a.keep:
            print(f"docs_img: work folder {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    for p in made:
        print(f"{p} {p.stat().st_size // 1024} kB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
