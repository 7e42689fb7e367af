"""C export (gpg/export.py): the generated source compiled with the system ``cc`` and called
through ctypes equals ``Surrogate.predict_mean`` (force, torque, levels, ``in_domain``), in
double to rounding and in float to float accuracy; bad exports are refused before anything
is written."""

import ctypes
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import export
from gpg.quadrotor.frames import airflow_frame_rate
from gpg.surrogate import MAX_FRAME_RATE, Surrogate
from tests.helpers import synthetic_dataset

CFG = {"hyper": {"fit": False, "lengthscale": 0.8}}
D = ctypes.POINTER(ctypes.c_double)


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(40, seed=3, raw=False)[0]


def compiled(sur, tmp_path, dtype):
    out = export.to_c(sur, tmp_path, name="quad", dtype=dtype)
    so = tmp_path / "quad.so"
    res = subprocess.run(
        ["cc", "-O2", "-std=c99", "-Wall", "-Werror", "-shared", "-fPIC", "-o", str(so),
         str(out["c"]), "-lm"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    lib = ctypes.CDLL(str(so))
    lib.quad_mean.argtypes = [D] * 6
    lib.quad_mean.restype = ctypes.c_int
    n_levels = len(sur.output_names) - 6

    def call(rpm, euler, v):
        f, t, lv = np.zeros(3), np.zeros(3), np.zeros(max(n_levels, 1))
        args = [np.ascontiguousarray(a, dtype=float) for a in (rpm, euler, v)]
        ok = lib.quad_mean(*(a.ctypes.data_as(D) for a in (*args, f, t, lv)))
        return ok, f, t, lv[:n_levels]

    return out, call


def states(n, seed):
    """Inside the box mostly, some outside (fast, sideways, backwards), some near vertical."""
    rng = np.random.default_rng(seed)
    rpm = rng.uniform(500, 6500, (n, 4))
    euler = rng.uniform([-np.pi, -0.9, -1.2], [np.pi, 0.9, 1.2], (n, 3))
    v = rng.uniform(-12, 12, (n, 3))
    v[: n // 4, :2] *= 1e-3  # near vertical airflow: the frame-rate flag's region
    return rpm, euler, v


@pytest.mark.parametrize("model", ["gpg", "gpgs_hybrid"])
@pytest.mark.parametrize("dtype", ["double", "float"])
def test_exported_c_equals_predict_mean(data, tmp_path, model, dtype):
    """Double: to rounding (1e-10 of the output's scale); float: the GP's arrays and kernel
    in float, sums in double, so to a few float roundings of each term (1e-5).
    ``in_domain`` equal wherever the frame rate is not within 1e-6 of its threshold (the C
    code takes central differences, the library autodiff)."""
    sur = Surrogate.fit(data, model, CFG)
    out, call = compiled(sur, tmp_path, dtype)
    rpm, euler, v = states(200, 1)
    ref = jax.jit(jax.vmap(sur.predict_mean))(rpm, euler, v)
    rate = np.asarray(jax.vmap(lambda e, w: airflow_frame_rate(e, w, sur.hover_speed))(
        jnp.asarray(euler), jnp.asarray(v)))  # fmt: skip
    rtol = 1e-10 if dtype == "double" else 1e-5
    flags = []
    for i in range(len(rpm)):
        ok, f, t, lv = call(rpm[i], euler[i], v[i])
        for got, want in ((f, ref.force[i]), (t, ref.torque[i]), (lv, ref.levels[i])):
            want = np.asarray(want)
            np.testing.assert_allclose(got, want, rtol=0, atol=rtol * max(1.0, np.abs(want).max()))
        if abs(rate[i] / MAX_FRAME_RATE - 1) > 1e-6:
            assert ok == bool(ref.in_domain[i]), (i, rate[i])
        flags.append(ok)
    assert 0 < sum(flags) < len(flags)  # both kinds of state were met
    assert out["constant_bytes"] == (40 * 8 + 40 * 9 * 8) * (8 if dtype == "double" else 4)
    text = out["h"].read_text()
    assert out["record"]["arrays_sha256"] in text and "int quad_mean(" in text


def test_non_finite_input_gives_zero_and_finite_values(data, tmp_path):
    sur = Surrogate.fit(data, "gpg", CFG)
    _, call = compiled(sur, tmp_path, "double")
    good = (np.full(4, 3600.0), np.zeros(3), np.array([3.0, 0.0, 0.0]))
    assert call(*good)[0] == 1
    for k in range(3):
        bad = [a.copy() for a in good]
        bad[k][0] = np.nan if k != 1 else np.inf
        ok, f, t, lv = call(*bad)
        assert ok == 0 and np.all(np.isfinite(np.r_[f, t, lv]))
    ok, f, t, _ = call(np.full(4, -10.0), np.zeros(3), np.array([3.0, 0.0, 0.0]))
    assert ok == 0 and np.all(np.isfinite(np.r_[f, t]))


def test_what_cannot_be_exported_is_refused_before_writing(data, tmp_path):
    import equinox as eqx

    local = Surrogate.fit(data, "gps_1x", {**CFG, "partition": {"bins": 2}})
    with pytest.raises(ValueError, match="has no global mean to export"):
        export.to_c(local, tmp_path / "a")
    sur = Surrogate.fit(data, "gpg", CFG)
    broken = eqx.tree_at(lambda s: s.model.mean.coef, sur, sur.model.mean.coef.at[0, 0].set(np.nan))
    with pytest.raises(ValueError, match=r"non-finite arrays \['coef'\]"):
        export.to_c(broken, tmp_path / "b")
    with pytest.raises(ValueError, match="name must be a C identifier"):
        export.to_c(sur, tmp_path / "c", name="my-model")
    with pytest.raises(ValueError, match="dtype must be one of"):
        export.to_c(sur, tmp_path / "d", dtype="half")
    with pytest.raises(ValueError, match="export takes a gpg.Surrogate"):
        export.to_c(sur.model, tmp_path / "e")
    assert not any((tmp_path / s).exists() for s in "abcde")


@pytest.mark.parametrize("frame", ["world", "body"])
def test_casadi_function_equals_predict_mean_and_its_jacobians(data, frame):
    """Values to rounding (1e-10 of each output's scale); CasADi's own Jacobian of force and
    torque in (rpm, euler, v_air) equals ``jax.jacrev`` of the library's prediction to 1e-8
    of its largest entry; ``in_domain`` as the library's (both autodiff the frame)."""
    import casadi as ca

    from gpg.surrogate import predict_state

    sur = Surrogate.fit(data, "gpgs_hybrid", CFG)
    f = export.to_casadi(sur, frame=frame)
    body = frame == "body"

    def wrench(r, e, v):
        p = predict_state(sur, r, e, v, False, body=body)
        return jnp.concatenate([p.force, p.torque, p.levels]), p.in_domain

    ref = jax.jit(wrench)
    jac = jax.jit(jax.jacrev(lambda r, e, v: wrench(r, e, v)[0][:6], argnums=(0, 1, 2)))
    syms = [ca.MX.sym(n, k) for n, k in (("rpm", 4), ("euler", 3), ("v", 3))]
    out = f(*syms)
    jf = ca.Function("j", syms, [ca.jacobian(ca.vertcat(out[0], out[1]), ca.vertcat(*syms))])
    rpm, euler, v = states(40, 2)
    seen = set()
    for i in range(len(rpm)):
        want, ok = (np.asarray(a) for a in ref(rpm[i], euler[i], v[i]))
        got = np.concatenate([np.asarray(a).ravel() for a in f(rpm[i], euler[i], v[i])[:3]])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * max(1.0, np.abs(want).max()))
        flag = float(f(rpm[i], euler[i], v[i])[3])
        assert flag == float(ok)
        seen.add(flag)
        Jj = np.concatenate([np.asarray(a) for a in jac(rpm[i], euler[i], v[i])], axis=1)
        Jc = np.asarray(jf(rpm[i], euler[i], v[i]))
        np.testing.assert_allclose(Jc, Jj, rtol=0, atol=1e-8 * np.abs(Jj).max())
    assert seen == {0.0, 1.0}
    with pytest.raises(ValueError, match="frame must be"):
        export.to_casadi(sur, frame="H")
