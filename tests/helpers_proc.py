"""Child processes of tests and of the docs-image tool: `python -m rsra …` that dies with its
parent, stopped by SIGINT (then killed), and headless Chromium as the suite drives it."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"]


def die_with_parent() -> None:
    """In the child before exec: SIGKILL when the parent dies (Linux)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def spawn(args, **kw) -> subprocess.Popen:
    """``python -m rsra *args`` as a child that dies with this process."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    pre = die_with_parent if sys.platform.startswith("linux") else None
    return subprocess.Popen([sys.executable, "-m", "rsra", *args], env=env, preexec_fn=pre,
                            text=True, **kw)


def stop(p: subprocess.Popen) -> None:
    """SIGINT (the commands' clean stop), then SIGKILL after 20 s."""
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


def launch_chromium(pw, profile: Path, width: int, height: int):
    """A persistent headless Chromium context (a fresh profile folder) at width × height, the
    system's browser (never Playwright's own download)."""
    return pw.chromium.launch_persistent_context(
        str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
        viewport={"width": width, "height": height})
