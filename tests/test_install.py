"""The package as a user gets it: built as a wheel, installed into a fresh virtual environment
outside the repository, it finds its vehicles and configs (package data), holds no experiment
code (gpg.runs only forwards to a checkout's experiments/), and runs the README's real-time
quick start. Slow: the venv installs gpg's dependencies (from pip's cache when warm)."""

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _quick_start() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    return next(b for b in blocks if "gpg.checkpoint.save" in b)


def test_wheel_installs_and_runs_the_quick_start_outside_the_repository(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(wheels),
            str(ROOT),
        ],
        check=True,
    )
    (wheel,) = wheels.glob("gpg-*.whl")
    with zipfile.ZipFile(wheel) as z:
        tops = {n.split("/")[0] for n in z.namelist() if not n.startswith("gpg-")}
        runs = [n for n in z.namelist() if n.startswith("gpg/runs/")]
    assert tops == {"gpg"} and runs == ["gpg/runs/__init__.py"], (tops, runs)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel)], check=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    check = (
        "import gpg, gpg.quadrotor as q\n"
        "from gpg.conf import load\n"
        "assert 'site-packages' in gpg.__file__, gpg.__file__\n"
        "assert {'sui_endurance', 'minimal_example'} <= set(q.vehicle.known_vehicles())\n"
        "assert load('smoke', 'data')['n_train'] > 0 and load('gpgs_hybrid', 'model')\n"
        # No experiment code installed; the old name says where it went.
        "import importlib.util as u, zipfile, sys\n"
        "assert u.find_spec('experiments') is None\n"
        "try:\n"
        "    import gpg.runs.compare\n"
        "    sys.exit('gpg.runs.compare imported outside a checkout')\n"
        "except ImportError as e:\n"
        "    assert 'experiments' in str(e), e\n"
        "from gpg.export.c_source import fragment\n"
        "assert '#define N_LEVELS' in fragment('body.c') and 'rot_wb' in fragment('frames.c')\n"
    )
    subprocess.run([str(py), "-c", check], cwd=work, check=True)
    out = subprocess.run(
        [str(py), "-c", _quick_start()], cwd=work, check=True, capture_output=True, text=True
    )
    assert "True" in out.stdout  # p.in_domain, printed by the quick start
