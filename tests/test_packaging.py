"""A plain, non-editable install carries the packages, the default config, EDS and scenarios."""
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_installs_and_runs_outside_the_repo(tmp_path):
    wheel_dir = tmp_path / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "-w", str(wheel_dir), str(ROOT)], check=True, capture_output=True)
    wheel = next(wheel_dir.glob("rsra-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert "rsra_config/rig.toml" in names
    assert "rsra_config/eds/load_cell.eds" in names
    # rsra web: its page and plugin always, Open MCT once `make web` has put it in place
    assert {"daq/web/web-static/index.html", "daq/web/web-static/rsra-plugin.js"} <= set(names)
    if (ROOT / "daq" / "web" / "openmct-dist" / "openmct.js").is_file():
        assert "daq/web/openmct-dist/openmct.js" in names
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(target), str(wheel)], check=True, capture_output=True)
    code = ("import estimator, daq.config as c; assert estimator.__file__.startswith(%r), "
            "estimator.__file__; cfg = c.load_config(); print(cfg.nodes[0].eds.is_file())"
            % str(target))
    out = subprocess.run([sys.executable, "-I", "-c",
                          f"import sys; sys.path.insert(0, {str(target)!r}); {code}"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "True"


def _backend_warnings(stderr: str) -> list[str]:
    return [line.strip() for line in stderr.splitlines() if "Warning" in line]


def test_building_the_wheel_prints_no_warning_and_matplotlib_is_a_dependency(tmp_path):
    """`project.license` as a table and data folders missing from `packages` made setuptools
    print ~200 lines on every install (issue 13)."""
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                          "-w", str(tmp_path), str(ROOT)], capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert _backend_warnings(out.stderr) == [], out.stderr
    wheel = next(tmp_path.glob("rsra-*.whl"))
    zf = zipfile.ZipFile(wheel)
    meta = zf.read(next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA")))
    requires = [line for line in meta.decode().splitlines() if line.startswith("Requires-Dist:")]
    # plots are a core feature: matplotlib without an extra marker
    assert any(r.split(":", 1)[1].strip().startswith("matplotlib") and "extra ==" not in r
               for r in requires), requires


def test_editable_install_the_way_make_runs_it_is_quiet(tmp_path):
    cmd = subprocess.run(["make", "-s", "-C", str(ROOT), "--eval",
                          "show-pip-install: ; @printf '%s\\n' '$(PIP_INSTALL)'",
                          "show-pip-install"], capture_output=True, text=True, check=True)
    pip_install = cmd.stdout.strip()
    assert "pip install" in pip_install, pip_install
    # the Makefile's command, into a throwaway prefix; --ignore-installed keeps pip from
    # uninstalling the project from the environment running this test
    prefix = tmp_path / "p"
    out = subprocess.run(f"{pip_install} --no-deps --ignore-installed --prefix {prefix} -e {ROOT}",
                         shell=True, cwd=ROOT, capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr + out.stdout
