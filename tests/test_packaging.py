"""A plain, non-editable install carries the packages, the default config, EDS and scenarios;
the editable install is a link tree static tools read."""
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One `pip wheel` of the repository for the tests of this file: (its output, the wheel)."""
    wheel_dir = tmp_path_factory.mktemp("wheel")
    # -v: the compiler's own output (the hub kernel's build) is in it
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-v", "--no-deps",
                          "-w", str(wheel_dir), str(ROOT)], capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    return out, next(wheel_dir.glob("rsra-*.whl"))


def test_wheel_installs_and_runs_outside_the_repo(tmp_path, built):
    """One import namespace (issue 15): the wheel's only top-level package is `rsra`; the
    packaged rig, EDS and scenarios come with it; `python -m rsra --help` runs outside the repo
    and no generic name (`daq`, `estimator`, `sim_bus`, `rsra_config`, `config`) is importable."""
    _, wheel = built
    names = zipfile.ZipFile(wheel).namelist()
    assert "rsra/config/rig.toml" in names
    assert "rsra/config/eds/load_cell.eds" in names
    assert "rsra/config/scenarios/ground-test.toml" in names
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"rsra"}, top
    # rsra web: its page and plugin always, Open MCT once `make web` has put it in place
    assert {"rsra/daq/web/web-static/index.html",
            "rsra/daq/web/web-static/rsra-plugin.js"} <= set(names)
    if (ROOT / "daq" / "web" / "openmct-dist" / "openmct.js").is_file():
        assert "rsra/daq/web/openmct-dist/openmct.js" in names
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(target), str(wheel)], check=True, capture_output=True)
    assert sorted(p.name for p in target.iterdir() if not p.name.endswith(".dist-info")
                  and p.name != "bin") == ["rsra"]
    code = ("import rsra.estimator as e, rsra.config.rig as c; "
            "assert e.__file__.startswith(%r), e.__file__; cfg = c.load_config(); "
            "print(cfg.nodes[0].eds.is_file())" % str(target))
    env = {"PATH": os.environ.get("PATH", ""), "PYTHONPATH": str(target)}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "True"
    helped = subprocess.run([sys.executable, "-m", "rsra", "--help"], cwd=tmp_path,
                            capture_output=True, text=True, env=env)
    assert helped.returncode == 0, helped.stderr
    assert "usage: rsra" in helped.stdout
    for generic in ("daq", "estimator", "sim_bus", "rsra_config", "config"):
        probe = subprocess.run([sys.executable, "-c", f"import {generic}"], cwd=tmp_path,
                               capture_output=True, text=True, env=env)
        assert probe.returncode != 0 and "No module named" in probe.stderr, generic


def _backend_warnings(stderr: str) -> list[str]:
    return [line.strip() for line in stderr.splitlines() if "Warning" in line]


def test_building_the_wheel_prints_no_warning_and_matplotlib_is_a_dependency(built):
    """`project.license` as a table and data folders missing from `packages` made setuptools
    print ~200 lines on every install (issue 13)."""
    out, wheel = built
    assert out.returncode == 0, out.stderr
    assert _backend_warnings(out.stderr) == [], out.stderr
    zf = zipfile.ZipFile(wheel)
    meta = zf.read(next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA")))
    requires = [line for line in meta.decode().splitlines() if line.startswith("Requires-Dist:")]
    # plots are a core feature: matplotlib without an extra marker
    assert any(r.split(":", 1)[1].strip().startswith("matplotlib") and "extra ==" not in r
               for r in requires), requires


def _make_variable(name: str, *args: str, cwd: Path = ROOT) -> str:
    cmd = subprocess.run(["make", "-s", "-C", str(cwd), *args, "--eval",
                          f"show-var: ; @printf '%s\\n' '$({name})'", "show-var"],
                         capture_output=True, text=True, check=True)
    return cmd.stdout.strip()


_SOURCES = ("rsra", "daq", "estimator", "sim_bus", "config")


def _copy_sources(dest: Path) -> Path:
    """The package folders, pyproject.toml, setup.py, README.md and the Makefile, copied."""
    import shutil

    skip = shutil.ignore_patterns("__pycache__", "*.so", "openmct-dist")
    for d in _SOURCES:
        shutil.copytree(ROOT / d, dest / d, ignore=skip, symlinks=True)  # rsra/daq: a link
    for f in ("pyproject.toml", "setup.py", "README.md", "Makefile"):
        shutil.copy2(ROOT / f, dest / f)
    return dest


def _site_python(venv: Path, code: str, cwd: Path) -> subprocess.CompletedProcess:
    """`code` run by the fresh `venv` (its site-packages, .pth files and all), with numpy and
    the rest from this environment on PYTHONPATH (whose own .pth files are not read)."""
    deps = next(p for p in sys.path if p.endswith("site-packages"))
    env = {"PATH": os.environ.get("PATH", ""), "PYTHONPATH": deps}
    return subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=cwd,
                          capture_output=True, text=True, env=env)


def test_editable_install_the_way_make_runs_it_is_quiet_and_a_link_tree_static_tools_read(
        tmp_path):
    """Issue 27: the Makefile's editable install is setuptools' strict mode, a tree of links
    on a .pth path (mypy, pyright and an IDE follow it) and no import-hook finder (they cannot);
    rsra.daq (daq/) and the compiled kernel are found through it, and from the top of the
    checkout through the links rsra/daq -> ../daq (where rsra/ comes first on sys.path); a file added to a package is importable
    once the install runs again (what the next `make` does, test below), and not before."""
    pip_editable = _make_variable("PIP_EDITABLE")
    assert "pip install" in pip_editable, pip_editable
    # the Makefile's command on a copy of the sources (the link tree goes into the copy's
    # build/, not this checkout's), into a throwaway prefix; --ignore-installed keeps pip from
    # uninstalling the project from the environment running this test
    src = _copy_sources(tmp_path / "src")
    prefix = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(prefix)], check=True)
    install = f"{pip_editable} {src} --no-deps --ignore-installed --prefix {prefix}"
    out = subprocess.run(install, shell=True, cwd=ROOT, capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr + out.stdout
    site = next(prefix.glob("lib/python*/site-packages"))
    assert not list(site.glob("__editable__*finder*")), sorted(p.name for p in site.iterdir())
    # the .pth holds one folder and no code: a static tool reads it as a search path
    (pth,) = site.glob("__editable__*.pth")
    lines = pth.read_text().split()
    assert len(lines) == 1 and not lines[0].startswith("import"), lines
    tree = Path(lines[0])
    assert (tree / "rsra" / "daq" / "__init__.py").resolve() == src / "daq" / "__init__.py"
    assert (tree / "rsra" / "estimator" / "filters.py").resolve() == \
        src / "estimator" / "filters.py"
    code = ("import rsra.daq, rsra.daq._hubkernel as k, rsra.canbus, rsra.config.rig as c; "
            "from pathlib import Path; print(Path(k.__file__).resolve().parent); "
            "print(c.load_config().nodes[0].eds.is_file())")
    for cwd in (tmp_path, src):
        ran = _site_python(prefix, code, cwd)
        assert ran.returncode == 0, ran.stderr
        assert ran.stdout.split() == [str(src / "daq"), "True"], ran.stdout
    # a new file: not linked until the install runs again
    (src / "estimator" / "brand_new.py").write_text("VALUE = 7\n")
    probe = "import rsra.estimator.brand_new as b; print(b.VALUE)"
    assert "No module named" in _site_python(prefix, probe, tmp_path).stderr
    subprocess.run(install, shell=True, cwd=ROOT, check=True, capture_output=True)
    ran = _site_python(prefix, probe, tmp_path)
    assert ran.returncode == 0 and ran.stdout.strip() == "7", ran.stderr


def test_a_file_added_to_a_package_makes_the_next_make_relink(tmp_path):
    """The link tree holds the files there were when it was made: the Makefile keeps a list
    of the package files and the install depends on it, so a new (or removed) file makes
    `make setup` run the install again, an edited one does not."""
    src = _copy_sources(tmp_path / "src")
    stamp = Path(_make_variable("STAMP", cwd=src))
    venv = src / ".venv"

    def up_to_date() -> bool:
        return subprocess.run(["make", "-q", "-C", str(src), "setup"],
                              capture_output=True).returncode == 0

    assert (venv / ".package-files").is_file()  # made by reading the Makefile (above)
    (src / stamp).touch()
    assert up_to_date()
    with open(src / "estimator" / "filters.py", "a") as f:
        f.write("\n# edited\n")
    assert up_to_date()
    (src / "sim_bus" / "brand_new.py").write_text("VALUE = 7\n")
    assert not up_to_date()
    (src / stamp).touch()
    assert up_to_date()
    (src / "sim_bus" / "brand_new.py").unlink()
    assert not up_to_date()


def test_the_wheel_builds_the_hub_kernel_with_no_compiler_warning_and_a_fresh_venv_loads_it(
        tmp_path, built):
    """The compiled hub path (issue 26) is built by `pip install .` / `pip wheel .` with the
    C compiler setuptools finds (gcc here, -Wall), with no warning, and a fresh venv that
    installs the wheel finds it and numpy's BLAS (rsra.daq.runtime.hubpath.load)."""
    out, wheel = built
    log = out.stdout + out.stderr
    assert "_hubkernel.c" in log, "the kernel was not compiled"
    compiler = [line for line in log.splitlines()
                if "_hubkernel" in line and ("warning:" in line or "error:" in line)]
    assert compiler == [], compiler
    assert any(n.startswith("rsra/daq/_hubkernel.") and n.endswith(".so")
               for n in zipfile.ZipFile(wheel).namelist())
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    vpy = venv / "bin" / "python"
    site = subprocess.run([str(vpy), "-c", "import sysconfig; print(sysconfig.get_paths()"
                           "['purelib'])"], capture_output=True, text=True, check=True)
    target = Path(site.stdout.strip())
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(target), str(wheel)], check=True, capture_output=True)
    # numpy and the rest from this environment, after the fresh venv's own site-packages
    deps = next(p for p in sys.path if p.endswith("site-packages"))
    code = ("from rsra.daq.runtime.hubpath import load; import rsra.daq._hubkernel as k; "
            "assert k.__file__.startswith(%r), k.__file__; kernel, why = load(); "
            "assert kernel is not None, why; print(why)" % str(target))
    env = {"PATH": os.environ.get("PATH", ""), "PYTHONPATH": deps}
    ran = subprocess.run([str(vpy), "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env=env)
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.startswith("compiled ("), ran.stdout


def test_rsra_version_prints_the_installed_version(capsys):
    """Issue 29: there was no `rsra --version`."""
    from importlib.metadata import version

    import pytest

    from rsra.daq.cli import main

    with pytest.raises(SystemExit) as ei:
        main(["--version"])
    assert ei.value.code == 0
    assert capsys.readouterr().out.strip() == f"rsra {version('rsra')}"
