"""Checkpoints under concurrent processes (slow: subprocess stress runs).

* Two processes save to the same path with ``overwrite=False`` in 100 rounds, released at the
  same moment: in every round exactly one succeeds, the other is told the path exists, and the
  checkpoint on disk is the winner's, complete (0 lost checkpoints).
* One process overwrites a checkpoint again and again while another loads it 1000 times: every
  load returns a complete checkpoint, one of the versions written (0 failures).
"""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gpg import checkpoint

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

SAVER = """
import json, sys, time
from pathlib import Path
from gpg import checkpoint
from gpg.checkpoint import CheckpointError
import dataclasses
src, root, me, rounds = sys.argv[1], Path(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
sur = dataclasses.replace(checkpoint.load(src), hover_speed=me)  # tells the writers apart
out = []
for r in range(rounds):
    go = root / f"go-{r}"
    while not go.exists():
        time.sleep(0.001)
    try:
        checkpoint.save(root / f"ck-{r}", sur)
        out.append("saved")
    except CheckpointError as exc:
        out.append("exists" if "exists" in str(exc) else repr(exc))
    except Exception as exc:
        out.append(repr(exc))
    (root / f"done-{r}-{me}").touch()
print(json.dumps(out))
"""

OVERWRITER = """
import sys
from pathlib import Path
import dataclasses
from gpg import checkpoint
src, path, n = sys.argv[1], Path(sys.argv[2]), int(sys.argv[3])
sur = checkpoint.load(src)
versions = [dataclasses.replace(sur, hover_speed=h) for h in (0.5, 0.6)]
for i in range(n):
    checkpoint.save(path, versions[i % 2], overwrite=True)
(path.parent / "writer-done").touch()
"""

READER = """
import json, sys
from pathlib import Path
from gpg import checkpoint
path, n = Path(sys.argv[1]), int(sys.argv[2])
failures, seen = [], set()
for i in range(n):
    try:
        s = checkpoint.load(path)
        seen.add(s.hover_speed)
    except Exception as exc:
        failures.append(repr(exc))
print(json.dumps({"failures": failures, "seen": sorted(seen)}))
"""


def _python(code, *args):
    return subprocess.Popen(
        [sys.executable, "-c", code, *map(str, args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture(scope="module")
def source(synthetic_surrogate, tmp_path_factory):
    return checkpoint.save(tmp_path_factory.mktemp("src") / "ck", synthetic_surrogate)


def test_two_exclusive_writers_never_lose_a_checkpoint(source, tmp_path):
    rounds = 100
    procs = [_python(SAVER, source, tmp_path, me, rounds) for me in (0.5, 0.6)]
    time.sleep(2)  # both have loaded; from here on they wait for each round's signal
    for r in range(rounds):
        (tmp_path / f"go-{r}").touch()
        deadline = time.time() + 60
        while not all((tmp_path / f"done-{r}-{me}").exists() for me in (0.5, 0.6)):
            for p in procs:
                if p.poll() is not None and p.returncode != 0:
                    pytest.fail(f"a writer failed: {p.stderr.read()[-2000:]}")
            assert time.time() < deadline, f"round {r} did not finish"
            time.sleep(0.002)
    outs = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=120)
        assert p.returncode == 0, stderr
        outs.append(json.loads(stdout.strip().splitlines()[-1]))
    lost = 0
    for r in range(rounds):
        got = sorted([outs[0][r], outs[1][r]])
        assert got == ["exists", "saved"], (r, got)
        winner = 0.5 if outs[0][r] == "saved" else 0.6
        back = checkpoint.load(tmp_path / f"ck-{r}")
        lost += back.hover_speed != winner
    assert lost == 0
    leftovers = [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]
    assert leftovers == []


def test_thousand_loads_during_overwrites(source, tmp_path):
    path = tmp_path / "ck"
    checkpoint.save(path, checkpoint.load(source))
    writer = _python(OVERWRITER, source, path, 60)
    reader = _python(READER, path, 1000)
    stdout, stderr = reader.communicate(timeout=1200)
    assert reader.returncode == 0, stderr
    res = json.loads(stdout.strip().splitlines()[-1])
    _, werr = writer.communicate(timeout=600)
    assert writer.returncode == 0, werr
    assert res["failures"] == [], res["failures"][:3]
    assert set(res["seen"]) == {0.5, 0.6}  # the reader did see the overwrites
    versions = [p for p in path.iterdir() if p.name.startswith("v-")]
    assert len(versions) == 1 and not [p for p in path.iterdir() if ".tmp" in p.name]
