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
