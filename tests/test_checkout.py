"""A plain checkout is the package (issue 50 item 7): run at the repository's top with no
install at all (no site-packages: ``python -S``), ``rsra.estimator`` is ``estimator/`` — the
links ``rsra/daq``, ``rsra/estimator``, ``rsra/sim_bus``, ``rsra/config`` point at the folders
the design card puts at the top, so mypy, pyright and an IDE follow ``rsra.*`` imports there."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TOP = Path(__file__).resolve().parent.parent
FOLDERS = ("daq", "estimator", "sim_bus", "config")


@pytest.mark.parametrize("name", FOLDERS)
def test_the_link_points_at_the_top_folder(name):
    link = TOP / "rsra" / name
    assert link.is_symlink() and os.readlink(link) == f"../{name}"
    assert link.resolve() == (TOP / name).resolve()


def test_find_spec_from_a_plain_checkout_names_the_top_folders():
    code = ("import importlib.util as u, os\n"
            "for m in ('rsra.estimator', 'rsra.daq.cli', 'rsra.sim_bus', 'rsra.config.rig'):\n"
            "    print(os.path.realpath(u.find_spec(m).origin))\n")
    out = subprocess.run([sys.executable, "-S", "-c", code], cwd=TOP, capture_output=True,
                         text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str((TOP / p).resolve()) for p in (
        "estimator/__init__.py", "daq/cli/__init__.py", "sim_bus/__init__.py", "config/rig.py")]
