"""A property-based layer over the entry points users feed by hand (hypothesis, derandomised so
that CI is reproducible): the CSV importer, dataset files, checkpoints and the query path. The
property each time: a clear ``ValueError`` (``CheckpointError`` for checkpoints) or a correct
result; never another exception, never a silently wrong or non-finite answer.

Run more examples with ``GPG_FUZZ_EXAMPLES=2000 .venv/bin/python -m pytest tests/test_fuzz.py``.
"""

import os
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpg import checkpoint
from gpg.checkpoint import CheckpointError
from gpg.data.dataset import Dataset, from_csv
from tests.data.test_dataset import COLUMNS
from tests.helpers import synthetic_dataset

SCALE = int(os.environ.get("GPG_FUZZ_EXAMPLES", "0"))
FAST = settings(
    max_examples=SCALE or 60,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
HEADER = list(COLUMNS.values())
# hypothesis shows each failing call's arguments; a surrogate's repr is large, not wrong.
pytestmark = pytest.mark.filterwarnings("ignore:Generating overly large repr")

numbers = st.floats(allow_nan=False, allow_infinity=False, width=32, min_value=0, max_value=1e4)
cells = st.one_of(
    numbers.map(repr),
    st.sampled_from(["nan", "inf", "-inf", "", " ", "1e309", "3,600.5", '"3,600.5"', "abc", "1_0"]),
    st.text(alphabet=st.characters(codec="utf-8"), max_size=6),
)


@st.composite
def csv_files(draw):
    """A CSV close to a valid one: the right header (sometimes a name twice, sometimes a BOM),
    rows of numbers with a few damaged cells, rows with a field too many or too few, and now
    and then a byte that is not UTF-8."""
    header = list(HEADER)
    if draw(st.booleans()) and draw(st.booleans()):
        i, j = draw(st.integers(0, 13)), draw(st.integers(0, 13))
        header[i] = header[j]
    n = draw(st.integers(0, 4))
    rows = []
    for _ in range(n):
        row = [repr(draw(numbers)) for _ in header]
        if draw(st.integers(0, 3)) == 0:
            row[draw(st.integers(0, 13))] = draw(cells)
        k = draw(st.integers(0, 9))
        if k == 0:
            row.append(repr(draw(numbers)))
        elif k == 1:
            row.pop()
        rows.append(row)
    text = ",".join(header) + "\n" + "".join(",".join(r) + "\n" for r in rows)
    raw = text.encode()
    if draw(st.integers(0, 5)) == 0:
        raw = b"\xef\xbb\xbf" + raw
    if draw(st.integers(0, 7)) == 0:
        at = draw(st.integers(0, len(raw) - 1))
        raw = raw[:at] + b"\xff" + raw[at:]
    return raw


@FAST
@given(raw=csv_files())
def test_csv_importer_is_right_or_says_why(raw, tmp_path_factory):
    f = tmp_path_factory.mktemp("csv") / "data.csv"
    f.write_bytes(raw)
    try:
        ds = from_csv(f, COLUMNS)
    except ValueError as exc:
        assert "data.csv" in str(exc) or "CSV" in str(exc)
        return
    # Accepted: then every row had the header's fields and every mapped cell was a number,
    # read in its own column (no shift).
    text = raw.decode("utf-8-sig")
    lines = [ln for ln in text.splitlines() if ln]
    header = lines[0].split(",")
    assert len(set(header)) == len(header)
    for i, ln in enumerate(lines[1:]):
        cells_ = ln.split(",")
        assert len(cells_) == len(header)
        for j, field in enumerate(("r1", "r2", "r3", "r4")):
            assert ds.x[i, j] == float(cells_[header.index(COLUMNS[field])])
    assert np.all(np.isfinite(ds.x)) and np.all(np.isfinite(ds.y_aero))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    root = tmp_path_factory.mktemp("files")
    ds, _ = synthetic_dataset(12, seed=4)
    ds.save(root / "ds")
    return root, ds


@FAST
@given(data=st.data())
def test_dataset_files_load_intact_or_say_why(saved, data, tmp_path_factory):
    root, ds = saved
    where = tmp_path_factory.mktemp("ds")
    for ext in (".npz", ".json"):
        shutil.copy(root / f"ds{ext}", where / f"ds{ext}")
    target = where / data.draw(st.sampled_from(["ds.npz", "ds.json"]))
    raw = bytearray(target.read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "delete"]))
    if kind == "flip":
        at = data.draw(st.integers(0, len(raw) - 1))
        raw[at] ^= 1 << data.draw(st.integers(0, 7))
        target.write_bytes(bytes(raw))
    elif kind == "truncate":
        target.write_bytes(bytes(raw[: data.draw(st.integers(0, len(raw) - 1))]))
    else:
        target.unlink()
    try:
        back = Dataset.load(where / "ds")
    except ValueError:
        return
    # Loaded despite the change (a flipped bit inside a number, say): whatever loads is a valid
    # dataset of the right shapes, finite (the checks of Dataset ran on it).
    assert back.x.shape == ds.x.shape and np.all(np.isfinite(back.x))


@pytest.fixture(scope="module")
def saved_checkpoint(synthetic_surrogate, tmp_path_factory):
    path = checkpoint.save(tmp_path_factory.mktemp("ck") / "ck", synthetic_surrogate)
    q = (np.full((3, 4), 3600.0), np.zeros((3, 3)), np.array([[5.0, 0, 0], [1, 1, 0], [0, 0, 0]]))
    return path, synthetic_surrogate.predict_batch(*q).force, q


@settings(FAST, max_examples=SCALE or 12)
@given(data=st.data())
def test_checkpoints_load_bit_for_bit_or_say_why(saved_checkpoint, data, tmp_path_factory):
    path, want, q = saved_checkpoint
    copy = tmp_path_factory.mktemp("ckc") / "ck"
    shutil.copytree(path, copy)
    files = sorted(p for p in copy.rglob("*") if p.is_file() and p.name != ".lock")
    target = files[data.draw(st.integers(0, len(files) - 1))]
    raw = bytearray(target.read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "delete"]))
    if kind == "flip" and raw:
        at = data.draw(st.integers(0, len(raw) - 1))
        raw[at] ^= 1 << data.draw(st.integers(0, 7))
        target.write_bytes(bytes(raw))
    elif kind == "truncate" and raw:
        target.write_bytes(bytes(raw[: data.draw(st.integers(0, len(raw) - 1))]))
    else:
        target.unlink()
    try:
        back = checkpoint.load(copy)
    except CheckpointError:
        return
    # Every byte that matters is checksummed: what loads predicts exactly what was saved.
    np.testing.assert_array_equal(back.predict_batch(*q).force, want)


values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.floats(min_value=-1e3, max_value=1e4),
)


@FAST
@given(
    rpm=st.lists(values, min_size=3, max_size=5),
    euler=st.lists(values, min_size=3, max_size=3),
    v=st.lists(values, min_size=2, max_size=3),
    kind=st.sampled_from(["float", "complex", "bool", "int"]),
)
def test_queries_are_answered_or_refused(synthetic_surrogate, rpm, euler, v, kind):
    sur = synthetic_surrogate
    cast = {"float": float, "complex": complex, "bool": bool, "int": int}[kind]
    try:
        args = [np.asarray([cast(x) for x in a]) for a in (rpm, euler, v)]
    except (ValueError, OverflowError):  # int(nan), int(inf): not a query one can make
        return
    try:
        p = sur.predict(*args)
    except ValueError:
        return
    assert kind in ("float", "int") and len(rpm) == 4 and len(v) == 3
    if bool(p.in_domain):  # an answer flagged in domain is a finite one
        for a in (p.force, p.torque, p.levels, p.variance):
            assert np.all(np.isfinite(np.asarray(a)))
