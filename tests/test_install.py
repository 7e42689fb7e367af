"""The package as a user gets it: built as a wheel, installed into a fresh virtual environment
outside the repository, it finds its vehicles and configs (package data) and runs the README's
real-time quick start. Slow: the venv installs gpg's dependencies (from pip's cache when warm)."""

import re
import subprocess
import sys
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
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel)], check=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    check = (
        "import gpg, gpg.quadrotor as q\n"
        "from gpg.runs.common import conf\n"
        "assert 'site-packages' in gpg.__file__, gpg.__file__\n"
        "assert {'sui_endurance', 'minimal_example'} <= set(q.vehicle.known_vehicles())\n"
        "assert conf('smoke', 'data')['n_train'] > 0 and conf('gpgs_hybrid', 'model')\n"
        "from gpg.export.c_source import fragment\n"
        "assert '#define N_LEVELS' in fragment('body.c') and 'rot_wb' in fragment('frames.c')\n"
    )
    subprocess.run([str(py), "-c", check], cwd=work, check=True)
    out = subprocess.run(
        [str(py), "-c", _quick_start()], cwd=work, check=True, capture_output=True, text=True
    )
    assert "True" in out.stdout  # p.in_domain, printed by the quick start
