"""C export (gpg/export/c_source.py): the generated source compiled with the system ``cc``
and called through ctypes equals ``Surrogate.predict`` (force, torque, levels, variance,
``in_domain``) for every exportable kind, in both frames, in double to rounding and in float
to float accuracy; bad exports are refused before anything is written."""

import ctypes
import subprocess

import jax
import numpy as np
import pytest

from gpg import export
from gpg.quadrotor.frames import airflow_frame_rate
from gpg.surrogate import MAX_FRAME_RATE
from tests.export.models import fitted, gp_attitude, rel_err, seam, states
from tests.helpers import variance_rtol

D = ctypes.POINTER(ctypes.c_double)
# The default model and exact GP-G in the fast set; PIC's shared rows and a slab partition
# with a binned mean (each a fit of its own) in the slow set, to keep the fast budget.
OTHER_KINDS = [pytest.param(k, d, marks=pytest.mark.slow)
               for k, d in (("gpg_pic", "float"), ("gpgs_schur", "double"))]  # fmt: skip
# The half turn's export here in the slow set: the fast set has it through the corrected
# model's (tests/flight/test_correction.py), whose C, CasADi and ONNX read it too.


def compiled(sur, tmp_path, dtype, cflags=(), **kw):
    out = export.to_c(sur, tmp_path, name="quad", dtype=dtype, **kw)
    so = tmp_path / "quad.so"
    res = subprocess.run(
        ["cc", "-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC", *cflags,
         "-o", str(so), str(out["c"]), "-lm"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    lib = ctypes.CDLL(str(so))
    n_levels = len(sur.output_names) - 6

    def call(rpm, euler, v, with_var=True):
        f, t, lv, var = np.zeros(3), np.zeros(3), np.zeros(max(n_levels, 1)), np.zeros(6 + n_levels)
        args = [np.ascontiguousarray(a, dtype=float).ctypes.data_as(D) for a in (rpm, euler, v)]
        outs = [a.ctypes.data_as(D) for a in (f, t, lv)]
        if with_var:
            ok = lib.quad_predict(*args, *outs, var.ctypes.data_as(D))
        else:
            ok = lib.quad_mean(*args, *outs)
        return ok, f, t, lv[:n_levels], var

    return out, call


@pytest.mark.parametrize(
    "kind, dtype",
    [("gpg", "double"), ("gpgs_hybrid", "float"), ("gpgs_hybrid_body", "double"),
     pytest.param("gpgs_hybrid_half", "double", marks=pytest.mark.slow), *OTHER_KINDS],
)  # fmt: skip
def test_exported_c_equals_predict(tmp_path, kind, dtype):
    """Mean: double to rounding (1e-10 of each output's scale); float: the GP's arrays and
    kernel in float, sums in double, so to a few float roundings of each term (1e-5).
    Variance: within the bound of ``variance_rtol`` (the stored factor's dtype, or float for
    a float export, and the conditioning of ``σ − ‖F k‖²``). ``in_domain`` equal wherever the
    frame rate is not within 1e-6 of its threshold (the C code takes central differences, the
    library its closed form). ``_half``: airflow from behind read at the state's half-turn
    image, its frame rate there; the states are all 1e-6 off that choice's seam."""
    sur = fitted(kind)
    out, call = compiled(sur, tmp_path, dtype)
    rpm, euler, v = states(50, 1, body=sur.frame == "body")
    ref = sur.predict_batch(rpm, euler, v)
    if sur.frame == "body":  # no frame rate: in_domain is the rotor box and the ball
        rate = np.zeros(len(rpm))
    else:
        rate = np.asarray(jax.jit(jax.vmap(lambda r, e, w: airflow_frame_rate(
            gp_attitude(sur, r, e, w), w, sur.hover_speed)))(rpm, euler, v))  # fmt: skip
        assert np.all(np.asarray(jax.vmap(lambda e, w: seam(sur, e, w))(euler, v)) > 1e-6)
    rtol = 1e-10 if dtype == "double" else 1e-5
    vtol = variance_rtol(sur, rpm, euler, v, None if dtype == "double" else 2.0**-24)

    def check(call, i):
        ok, f, t, lv, var = call(rpm[i], euler[i], v[i])
        for got, want in ((f, ref.force[i]), (t, ref.torque[i]), (lv, ref.levels[i])):
            assert rel_err(got, want) <= rtol, (i, got, want)
        want_var = np.asarray(ref.variance[i])
        assert np.all(np.abs(var - want_var) <= vtol[i] * want_var), (i, var, want_var)
        if abs(rate[i] / MAX_FRAME_RATE - 1) > 1e-6:
            assert ok == bool(ref.in_domain[i]), (i, rate[i])
        ok2, *mean = call(rpm[i], euler[i], v[i], with_var=False)[:4]
        assert ok2 == ok and all(
            np.array_equal(a, b) for a, b in zip(mean, (f, t, lv), strict=True)
        )
        return ok

    flags = [check(call, i) for i in range(len(rpm))]
    assert 0 < sum(flags) < len(flags)  # both kinds of state were met
    if kind == "gpgs_hybrid":  # the variance's other versions than this CPU's
        for i, cflags in enumerate((["-DGPG_NO_AVX512"], ["-DGPG_NO_CLONES", "-DGPG_NO_VECTOR"])):
            (tmp_path / str(i)).mkdir()
            other = compiled(sur, tmp_path / str(i), dtype, cflags)[1]
            assert [check(other, j) for j in range(10)] == flags[:10]
    text = out["h"].read_text()
    assert out["record"]["arrays_sha256"] in text and "int quad_predict(" in text
    assert out["variance"] and out["record"]["model"] == kind.removesuffix("_body").removesuffix(
        "_half"
    )
    assert out["record"]["half_turn"] == kind.endswith("_half")
    assert out["record"]["gp_frame"] == sur.frame
    d = np.asarray(sur.box_lo).size
    assert f"#define QUAD_N_INPUTS {d}" in text and f"quad_box_lo[{d}]" in text


def test_mean_only_export_and_its_constants(tmp_path):
    """``variance=False``: only ``<name>_mean``, and the constants are the global mean's
    arrays alone, in the bytes of the dtype asked for. Built with ``-DGPG_NO_CLONES`` (the
    code a CPU without AVX2, or another compiler, runs) it gives the same values to rounding:
    the AVX2 clone differs by FMA contraction only, a rounding of each term of the mean's
    cancelling sum, so the bound is the one held against predict (1e-10 of the scale). Built
    with ``-DGPG_NO_AVX512`` (what a CPU with AVX2 alone runs) it gives the same bits, and so
    it does with its sums' blocks of points made small (``-DGPG_MEAN_BLOCK``: many blocks and
    a shorter last one). The rows of the mean's blocks are padded to whole vectors of four."""
    sur = fitted("gpg")
    n, c = np.asarray(sur.model.mean.coef).shape
    block = next(b for b in (3, 5, 7) if n % b)  # several blocks, the last one shorter
    state = (np.full(4, 3600.0), np.array([0.1, -0.05, 0.02]), np.array([3.0, 0.5, -0.2]))
    for dtype, size in (("double", 8), ("float", 4)):
        (tmp_path / dtype).mkdir()
        out, call = compiled(sur, tmp_path / dtype, dtype, variance=False)
        ok, *vals = call(*state, with_var=False)[:4]
        assert ok
        (tmp_path / dtype / "generic").mkdir()
        _, generic = compiled(sur, tmp_path / dtype / "generic", dtype, ("-DGPG_NO_CLONES",),
                              variance=False)  # fmt: skip
        ok2, *vals2 = generic(*state, with_var=False)[:4]
        assert ok2 and all(rel_err(a, b) <= 1e-10 for a, b in zip(vals2, vals, strict=True))
        # the AVX2 version beside the AVX-512 one (where the CPU has it; else the same code):
        # the same operations in the same order per element, so the same bits
        (tmp_path / dtype / "avx2").mkdir()
        _, avx2 = compiled(sur, tmp_path / dtype / "avx2", dtype, ("-DGPG_NO_AVX512",),
                           variance=False)  # fmt: skip
        ok3, *vals3 = avx2(*state, with_var=False)[:4]
        assert ok3 and all(np.array_equal(a, b) for a, b in zip(vals3, vals, strict=True))
        (tmp_path / dtype / "blocks").mkdir()
        small = ("-DGPG_NO_AVX512", f"-DGPG_MEAN_BLOCK={block}")
        _, blocks = compiled(sur, tmp_path / dtype / "blocks", dtype, small, variance=False)
        ok4, *vals4 = blocks(*state, with_var=False)[:4]
        assert ok4 and all(np.array_equal(a, b) for a, b in zip(vals4, vals, strict=True))
        m = len(sur.output_names)  # positions and the mean's value block in double
        w0, wg = -(-m // 4) * 4, -(-(c - m) // 4) * 4
        assert out["constant_bytes"] == n * 8 * 8 + n * w0 * 8 + (n * wg + 8 + 1) * size
        assert not out["variance"] and "quad_predict" not in out["h"].read_text()


def test_non_finite_input_gives_zero_and_finite_values(tmp_path):
    _, call = compiled(fitted("gpgs_hybrid"), tmp_path, "double")
    good = (np.full(4, 3600.0), np.zeros(3), np.array([3.0, 0.0, 0.0]))
    assert call(*good)[0] == 1
    for k in range(3):
        bad = [a.copy() for a in good]
        bad[k][0] = np.nan if k != 1 else np.inf
        ok, f, t, lv, var = call(*bad)
        assert ok == 0 and np.all(np.r_[f, t, lv, var] == 0)
    ok, f, t, _, var = call(np.full(4, -10.0), np.zeros(3), np.array([3.0, 0.0, 0.0]))
    assert ok == 0 and np.all(np.isfinite(np.r_[f, t, var]))


def test_what_cannot_be_exported_is_refused_before_writing(tmp_path):
    import equinox as eqx

    from tests.helpers import synthetic_dataset

    sur = fitted("gpg")
    broken = eqx.tree_at(lambda s: s.model.mean.coef, sur, sur.model.mean.coef.at[0, 0].set(np.nan))
    with pytest.raises(ValueError, match=r"non-finite arrays \['alpha', 'coef'\]"):
        export.to_c(broken, tmp_path / "a")
    with pytest.raises(ValueError, match="name must be a C identifier"):
        export.to_c(sur, tmp_path / "b", name="my-model")
    with pytest.raises(ValueError, match="dtype must be one of"):
        export.to_c(sur, tmp_path / "c", dtype="half")
    with pytest.raises(ValueError, match="export takes a gpg.Surrogate"):
        export.to_c(sur.model, tmp_path / "d")
    with pytest.raises(ValueError, match=r"MiB of constants, over max_bytes=0\.1 MiB"):
        export.to_c(sur, tmp_path / "e", max_bytes=100_000)
    from gpg.quadrotor.simple_noise import SimpleNoise

    noisy = eqx.tree_at(lambda s: s.noise_model, sur, SimpleNoise.__new__(SimpleNoise),
                        is_leaf=lambda x: x is None)  # fmt: skip
    with pytest.raises(ValueError, match="M_noise cannot be exported"):
        export.to_c(noisy, tmp_path / "f")
    new = synthetic_dataset(8, seed=9, raw=False)[0]
    inside = np.all((new.x >= np.asarray(sur.box_lo)) & (new.x <= np.asarray(sur.box_hi)), axis=1)
    grown = sur.condition(new.subset(np.flatnonzero(inside)))
    with pytest.raises(ValueError, match="variance=False"):
        export.to_c(grown, tmp_path / "g")
    assert not any((tmp_path / s).exists() for s in "abcdefg")
    export.to_c(grown, tmp_path / "h", variance=False)  # its mean exports


def test_converted_data_export_with_their_directions(tmp_path):
    """A hybrid on converted paper-style data (directional gradient rows, :mod:`gpg.data.convert`)
    exports mean and variance: the C code's variance is ``predict``'s to rounding, its mean
    likewise. A double export of float64 factors: ``variance_rtol``'s bound on the quadratic
    form is at most 5e-11 at these states, and the folded factor ``F P`` sums at most three
    terms more per entry; 1e-9 holds that with room."""
    from gpg import Surrogate
    from gpg.data.convert import to_body
    from tests.helpers import synthetic_dataset

    air, _ = synthetic_dataset(40, seed=9, raw=False)
    sur = Surrogate.fit(to_body(air), "gpgs_hybrid", {
        "hyper": {"fit": False, "lengthscale": 0.9}, "partition": {"scheme": "kdtree"},
        "variance_dtype": "float64"})  # fmt: skip
    assert sur.model.local.bases is not None
    _, call = compiled(sur, tmp_path, "double")
    rpm, euler, v = states(20, 3, body=True)
    ref = sur.predict_batch(rpm, euler, v)
    for i in range(len(rpm)):
        ok, f, t, _, var = call(rpm[i], euler[i], v[i])
        assert rel_err(f, ref.force[i]) <= 1e-10 and rel_err(t, ref.torque[i]) <= 1e-10
        want = np.asarray(ref.variance[i])
        np.testing.assert_allclose(var, want, rtol=1e-9)
        assert ok == bool(ref.in_domain[i])
