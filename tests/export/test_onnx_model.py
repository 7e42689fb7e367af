"""ONNX export (gpg/export/onnx_model.py): ONNX Runtime runs the model, and its batched
float32 prediction equals ``Surrogate.predict`` to float32 accuracy, in both frames."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import export
from gpg.quadrotor.frames import R_WB, airflow_frame_rate, to_airflow_frame
from gpg.surrogate import MAX_FRAME_RATE, gp_inputs
from tests.export.models import fitted, gp_attitude, rel_err, seam, states
from tests.helpers import variance_rtol

ort = pytest.importorskip("onnxruntime")
U32 = 2.0**-24


def run(path, rpm, euler, v):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {"rpm": rpm, "euler": euler, "v_air": v}
    res = sess.run(None, {k: np.asarray(a, np.float32) for k, a in feeds.items()})
    return dict(zip([o.name for o in sess.get_outputs()], res, strict=True)), sess


@pytest.mark.parametrize(
    "kind",
    ["gpgs_hybrid", "gpgs_hybrid_body", pytest.param("gpgs_hybrid_half", marks=pytest.mark.slow),
     pytest.param("gpgs", marks=pytest.mark.slow)],
)  # fmt: skip
def test_onnx_runtime_equals_predict(tmp_path, kind):
    """The batched graph, airflow and body frame, and airflow from behind read at the
    half-turn image (``assert_equals_predict``'s bounds)."""
    sur = fitted(kind)
    out = export.to_onnx(sur, tmp_path / "m.onnx")
    rpm, euler, v = states(60, 4, body=sur.frame == "body")
    got, sess = run(out["onnx"], rpm, euler, v)
    assert [i.name for i in sess.get_inputs()] == ["rpm", "euler", "v_air"]
    assert_equals_predict(sur, got, rpm, euler, v)


@pytest.mark.parametrize(
    "kind", ["gpgs_hybrid", pytest.param("gpgs_schur", marks=pytest.mark.slow)]
)
def test_single_state_graph_equals_the_batched_one(tmp_path, kind):
    """``batch=False``: one state a run, the bin found by ``If`` nodes along the partition's
    tree (a k-d tree for the hybrid; a slab's cuts for gpgs_schur, in the slow set for its
    fit), only that bin evaluated. At states in every bin it gives the batched graph's
    outputs (which the test above holds against ``predict``): the same float32 inputs and
    operations, so ``in_domain`` is equal and the values differ only by the order of ONNX
    Runtime's sums for one row against many. For the mean, the 1e-5 of the scale held against
    ``predict``. For the variance, twice ``variance_rtol``'s bound at float32 (one for each
    graph) and 16 u for the last products."""
    from gpg.export import layout

    sur = fitted(kind)
    out = export.to_onnx(sur, tmp_path / "one.onnx", batch=False)
    assert out["record"]["batch"] is False
    rpm, euler, v = states(40, 5)
    want, _ = run(export.to_onnx(sur, tmp_path / "all.onnx")["onnx"], rpm, euler, v)
    sess = ort.InferenceSession(str(out["onnx"]), providers=["CPUExecutionProvider"])
    assert [i.shape for i in sess.get_inputs()] == [[1, 4], [1, 3], [1, 3]]
    names = [o.name for o in sess.get_outputs()]
    rows = []
    for i in range(len(rpm)):
        feeds = {"rpm": rpm[i : i + 1], "euler": euler[i : i + 1], "v_air": v[i : i + 1]}
        rows.append(sess.run(None, {k: np.asarray(a, np.float32) for k, a in feeds.items()}))
    got = {k: np.concatenate([r[j] for r in rows]) for j, k in enumerate(names)}
    assert np.array_equal(got["in_domain"], want["in_domain"])
    for key in ("force", "torque", "levels"):
        assert np.all(rel_err(got[key], want[key]) <= 1e-5), key
    tol = (2 * variance_rtol(sur, rpm, euler, v, U32)[:, None] + 16 * U32) * want["variance"]
    assert np.all(np.abs(got["variance"] - want["variance"]) <= tol)
    s = layout.spec(sur)

    @jax.jit
    @jax.vmap
    def xn(r, e, w):
        eh, speed, _ = to_airflow_frame(e, w, sur.hover_speed)
        return sur.normalizer.x(jnp.concatenate([r, eh, speed[None]]))

    seen = {s.bins.lookup(x) for x in np.asarray(xn(rpm, euler, v))}
    assert seen == set(range(s.bins.n_bins)) and s.bins.n_bins > 1


def assert_equals_predict(sur, got, rpm, euler, v):
    """ONNX Runtime's outputs ``got`` at the states against ``Surrogate.predict``.
    Mean to 1e-5 of each output's scale. Variance: the states enter in float32, so besides
    the bound of ``variance_rtol`` at float32's unit roundoff the variance moves by its
    gradient times the inputs' rounding (16 u of each input, the frame's few operations
    included), and the last products are float32 (16 u). ``in_domain`` equal except within
    1e-3 of the frame-rate threshold (a float32 central difference) or 1e-5 of a box face
    (or of the body frame's ball)."""
    ref = sur.predict_batch(rpm, euler, v)
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

    @jax.jit  # one program: op by op it compiled dozens
    @jax.vmap
    def margins(r, e, w):
        if sur.frame == "body":  # the rotor box and the ball's surface; no frame rate
            x = r
            ball = jnp.abs(jnp.linalg.norm(R_WB(e).T @ w) - sur.ball_radius)
            rate = jnp.zeros(())
        else:  # the half-turn image's where it is read; the seam 1e-3 away (float32's choice)
            x = gp_inputs(sur, r, e, w)[0]
            ball, rate = jnp.inf, airflow_frame_rate(gp_attitude(sur, r, e, w), w, sur.hover_speed)
            ball = jnp.where(seam(sur, e, w) > 1e-3, ball, 0.0)
        n = x.size
        face = jnp.min(jnp.abs(jnp.concatenate([x - sur.box_lo[:n], sur.box_hi[:n] - x])))
        return jnp.minimum(face, ball), rate

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
