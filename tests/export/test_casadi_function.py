"""CasADi export (gpg/export/casadi_function.py): values and variances equal
``Surrogate.predict``, CasADi's own Jacobians equal ``jax.jacrev`` of the library's
prediction, in the world and the body frame, for a global-mean and a binned-mean kind, and for
a surrogate fitted in the body frame (no airflow frame anywhere: its Jacobians are smooth at
hover and in vertical air)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import export
from gpg.surrogate import predict_state
from tests.export.models import fitted, rel_err, seam, states
from tests.helpers import variance_rtol

ca = pytest.importorskip("casadi")


@pytest.mark.parametrize(
    ("kind", "frame"),
    [
        ("gpgs_hybrid", "world"),
        ("gpgs_hybrid_body", "world"),
        pytest.param("gpgs_hybrid_half", "body", marks=pytest.mark.slow),
        pytest.param("gpgs", "body", marks=pytest.mark.slow),
    ],
)  # the binned kind's own fit: the slow set, for the fast budget
def test_casadi_function_equals_predict_and_its_jacobians(kind, frame):
    """Values to rounding (1e-10 of each output's scale), variances within
    ``variance_rtol``; the Jacobian of force and torque in (rpm, euler, v_air) to 1e-8 of its
    largest entry, and, for gpgs (float64 factors), of the variance too; ``in_domain`` as the
    library's (both autodiff the frame). ``_half``: airflow from behind read at the state's
    half-turn image (the states 1e-6 off the seam of that choice), in the body frame."""
    sur = fitted(kind)
    f = export.to_casadi(sur, frame=frame)
    body = frame == "body"

    def pred(r, e, v):
        p = predict_state(sur, r, e, v, True, body=body)
        return jnp.concatenate([p.force, p.torque, p.levels]), p.variance, p.in_domain

    ref = jax.jit(pred)
    jac = jax.jit(jax.jacrev(lambda *a: jnp.concatenate([pred(*a)[0][:6], pred(*a)[1]]),
                             argnums=(0, 1, 2)))  # fmt: skip
    syms = [ca.MX.sym(n, k) for n, k in (("rpm", 4), ("euler", 3), ("v", 3))]
    out = f(*syms)
    wrt = ca.vertcat(*syms)
    jf = ca.Function("j", syms, [ca.jacobian(ca.vertcat(out[0], out[1], out[3]), wrt)])
    rpm, euler, v = states(30, 2, body=sur.frame == "body")
    if sur.half_turn:
        assert np.all(np.asarray(jax.vmap(lambda e, w: seam(sur, e, w))(euler, v)) > 1e-6)
    vtol = variance_rtol(sur, rpm, euler, v)
    seen = set()
    for i in range(len(rpm)):
        want, want_var, ok = (np.asarray(a) for a in ref(rpm[i], euler[i], v[i]))
        res = [np.asarray(a).ravel() for a in f(rpm[i], euler[i], v[i])]
        assert rel_err(np.concatenate(res[:3]), want) <= 1e-10
        assert np.all(np.abs(res[3] - want_var) <= vtol[i] * want_var)
        assert float(res[4][0]) == float(ok)
        seen.add(float(ok))
        Jj = np.concatenate([np.asarray(a) for a in jac(rpm[i], euler[i], v[i])], axis=1)
        Jc = np.asarray(jf(rpm[i], euler[i], v[i]))
        rows = slice(None) if kind == "gpgs" else slice(0, 6)  # the factors' dtype
        np.testing.assert_allclose(Jc[rows], Jj[rows], rtol=0, atol=1e-8 * np.abs(Jj[rows]).max())
    assert seen == {0.0, 1.0}
    assert f.name_out() == ["force", "torque", "levels", "variance", "in_domain"]


def test_casadi_mean_only_and_bad_frame():
    sur = fitted("gpg")
    f = export.to_casadi(sur, variance=False, name="m")
    assert f.name_out() == ["force", "torque", "levels", "in_domain"] and f.name() == "m"
    with pytest.raises(ValueError, match="frame must be"):
        export.to_casadi(sur, frame="H")
