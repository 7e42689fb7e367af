"""ONNX export (gpg/export/onnx_model.py): ONNX Runtime runs the model, and its batched
float32 prediction equals ``Surrogate.predict`` to float32 accuracy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import export
from tests.export.models import fitted, rel_err, states
from tests.helpers import variance_rtol

ort = pytest.importorskip("onnxruntime")
U32 = 2.0**-24


def run(path, rpm, euler, v):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {"rpm": rpm, "euler": euler, "v_air": v}
    res = sess.run(None, {k: np.asarray(a, np.float32) for k, a in feeds.items()})
    return dict(zip([o.name for o in sess.get_outputs()], res, strict=True)), sess


@pytest.mark.parametrize("kind", ["gpgs_hybrid", pytest.param("gpgs", marks=pytest.mark.slow)])
def test_onnx_runtime_equals_predict(tmp_path, kind):
    """Mean to 1e-5 of each output's scale. Variance: the states enter in float32, so besides
    the bound of ``variance_rtol`` at float32's unit roundoff the variance moves by its
    gradient times the inputs' rounding (16 u of each input, the frame's few operations
    included), and the last products are float32 (16 u). ``in_domain`` equal except within
    1e-3 of the frame-rate threshold (a float32 central difference) or 1e-5 of a box face."""
    sur = fitted(kind)
    out = export.to_onnx(sur, tmp_path / "m.onnx")
    rpm, euler, v = states(60, 4)
    got, sess = run(out["onnx"], rpm, euler, v)
    assert [i.name for i in sess.get_inputs()] == ["rpm", "euler", "v_air"]
    ref = jax.jit(jax.vmap(sur.predict))(rpm, euler, v)
    for key in ("force", "torque", "levels"):
        assert np.all(rel_err(got[key], getattr(ref, key)) <= 1e-5), key
    want_var = np.asarray(ref.variance)
    grad = jax.jit(jax.vmap(jax.jacfwd(lambda r, e, w: sur.predict(r, e, w).variance,
                                       argnums=(0, 1, 2))))(rpm, euler, v)  # fmt: skip
    step = [16 * U32 * np.maximum(np.abs(a), 1.0) for a in (rpm, euler, v)]
    moved = sum(
        np.einsum("qcj,qj->qc", np.abs(np.asarray(J)), s) for J, s in zip(grad, step, strict=True)
    )
    # + the weights, the rotation and the output itself in float32: 16 u of the variance
    tol = (variance_rtol(sur, rpm, euler, v, U32)[:, None] + 16 * U32) * want_var + moved
    bad = np.argwhere(np.abs(got["variance"] - want_var) > tol)
    assert bad.size == 0, [
        (q, c, got["variance"][q, c], want_var[q, c], tol[q, c]) for q, c in bad[:5]
    ]
    from gpg.quadrotor.frames import airflow_frame_rate, to_airflow_frame
    from gpg.surrogate import MAX_FRAME_RATE

    @jax.vmap
    def margins(r, e, w):
        eh, speed, _ = to_airflow_frame(e, w, sur.hover_speed)
        x = jnp.concatenate([r, eh, speed[None]])
        face = jnp.min(jnp.abs(jnp.concatenate([x - sur.box_lo, sur.box_hi - x])))
        return face, airflow_frame_rate(e, w, sur.hover_speed)

    face, rate = (np.asarray(a) for a in margins(*(jnp.asarray(a) for a in (rpm, euler, v))))
    clear = (face > 1e-5) & (np.abs(rate / MAX_FRAME_RATE - 1) > 1e-3)
    assert np.array_equal(got["in_domain"][clear], np.asarray(ref.in_domain)[clear])
    assert 0 < got["in_domain"].sum() < len(rpm)


def test_onnx_non_finite_input_record_and_refusals(tmp_path):
    import onnx

    sur = fitted("gpg")
    out = export.to_onnx(sur, tmp_path / "g.onnx", variance=False)
    rpm, euler, v = np.full((3, 4), 3600.0), np.zeros((3, 3)), np.tile([3.0, 0.0, 0.0], (3, 1))
    rpm[1, 2], v[2, 0] = np.nan, np.inf
    got, sess = run(out["onnx"], rpm, euler, v)
    assert "variance" not in got
    assert got["in_domain"].tolist() == [True, False, False]
    assert np.all(got["force"][1:] == 0) and np.all(np.isfinite(got["force"]))
    props = {p.key: p.value for p in onnx.load(str(out["onnx"])).metadata_props}
    assert props["model"] == "gpg" and props["arrays_sha256"] == out["record"]["arrays_sha256"]
    with pytest.raises(ValueError, match="max_bytes"):
        export.to_onnx(sur, tmp_path / "h.onnx", max_bytes=1000)
    assert not (tmp_path / "h.onnx").exists()
