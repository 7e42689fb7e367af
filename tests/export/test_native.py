"""gpg.export.to_native: the C export built by the system's cc and called through ctypes,
against the library's predict (the online update's check is the bank's C test,
tests/flight/test_bank.py, which drives the bank through it)."""

import gc
import shutil
import tempfile

import numpy as np
import pytest

from gpg.export import Native, to_native
from tests.export.test_c_source import rel_err, states
from tests.helpers import variance_rtol

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


def test_native_predicts_as_predict(synthetic_surrogate, tmp_path):
    """Double: the loads to 1e-10 of their scale and the variance within ``variance_rtol``
    (the bounds the C export is held to); a non-finite input gives zeros and
    ``in_domain`` False; the export's files stay where they were asked to be written; a model
    with no online term refuses ``update`` and ``reset`` by name."""
    sur = synthetic_surrogate
    nat = to_native(sur, tmp_path, name="quad")
    assert isinstance(nat, Native) and not nat.online and nat.state is None
    assert len(list(tmp_path.glob("quad-*.so"))) == 1 and (tmp_path / "quad.h").exists()
    rpm, euler, v = states(12, 3)
    ref = sur.predict_batch(rpm, euler, v)
    vtol = variance_rtol(sur, rpm, euler, v, None)
    for i in range(len(rpm)):
        p = nat.predict(rpm[i], euler[i], v[i])
        assert rel_err(p.force, ref.force[i]) <= 1e-10 and rel_err(p.torque, ref.torque[i]) <= 1e-10
        assert p.levels.shape == (len(sur.output_names) - 6,)
        want = np.asarray(ref.variance[i])
        assert np.all(np.abs(p.variance - want) <= vtol[i] * want), i
        assert p.in_domain == bool(ref.in_domain[i])
    bad = nat.predict(rpm[0], euler[0], np.array([np.nan, 0.0, 0.0]))
    assert not bad.in_domain and not np.any(bad.force) and np.all(np.isfinite(bad.variance))
    with pytest.raises(ValueError, match="update: the model has no online term"):
        nat.update(0.0, rpm[0], euler[0], v[0], np.zeros(3), np.zeros(3), np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="reset: the model has no online term"):
        nat.reset()
    with pytest.raises(ValueError, match=r"euler must have shape \(3,\), got \(4,\)"):
        nat.predict(rpm[0], rpm[0], v[0])
    # another export under the same name and directory loads its own library (dlopen of a
    # path already loaded would hand back the first): float's arrays round differently
    f32 = to_native(sur, tmp_path, name="quad", dtype="float")
    a, b = f32.predict(rpm[1], euler[1], v[1]), nat.predict(rpm[1], euler[1], v[1])
    assert not np.array_equal(a.force, b.force) and rel_err(a.force, b.force) <= 1e-5
    assert len(list(tmp_path.glob("quad-*.so"))) == 2
    again = to_native(sur, tmp_path, name="quad")  # the same source: the same library
    assert len(list(tmp_path.glob("quad-*.so"))) == 2
    q = (rpm[2], euler[2], v[2])
    np.testing.assert_array_equal(again.predict(*q).force, nat.predict(*q).force)


def test_native_without_variance_a_temporary_build_and_bad_compilers(
    synthetic_surrogate, tmp_path, monkeypatch
):
    """``variance=False`` calls ``<name>_mean`` (the same loads, no variance); without a
    directory the build lives in a temporary one, removed with the object; a compiler that is
    not there is named, one that fails says so with its message and leaves no directory."""
    sur = synthetic_surrogate
    nat = to_native(sur, variance=False)
    where = nat.directory
    rpm, euler, v = states(3, 5)
    p, q = nat.predict(rpm[0], euler[0], v[0]), sur.predict(rpm[0], euler[0], v[0])
    assert p.variance is None and rel_err(p.force, q.force) <= 1e-10
    assert where.exists()
    del nat, p
    gc.collect()
    assert not where.exists()
    with pytest.raises(ValueError, match="no C compiler 'no-such-cc'"):
        to_native(sur, cc="no-such-cc")
    # a failed build leaves no temporary directory behind
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(RuntimeError, match="cc failed on"):
        to_native(sur, flags=("-std=c99", "-DGPG_NATIVE_TEST", "-include", "/nonexistent.h"))
    assert list(tmp_path.iterdir()) == []
