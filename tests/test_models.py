"""Model registry: every baseline builds and predicts through the same interface."""

import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import models
from gpg.data.preprocess import prepare, simple_model_for
from gpg.names import GRAD_DIMS
from tests.helpers import synthetic_dataset

FAST = {
    "hyper": {"fit": False, "lengthscale": 1.0},
    "partition": {"bins": 3, "points_per_bin": None},
    "near": {"budget": 0.5, "points": None},
    "inducing": {"points": 8},
}


@pytest.fixture(scope="module")
def training(request):
    from gpg.quadrotor.vehicle import load_vehicle

    ds, _ = synthetic_dataset(40)
    return prepare(ds, simple_model_for(ds, load_vehicle()))


# The FAST lengthscale makes the far sets correlated: the Schur models rightly warn.
pytestmark = pytest.mark.filterwarnings("ignore::gpg.gp.schur.SchurAssumptionWarning")


@pytest.mark.parametrize("name", models.NAMES)
def test_every_model_builds_and_predicts(training, name):
    built = models.build(name, training, models.restrict(name, FAST))
    Xq = training.X[:7] * 0.9
    mean, var = built.model.predict(Xq)
    assert mean.shape == (7, 9) and var.shape == (7,)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    np.testing.assert_allclose(built.model.predict_mean(Xq), mean, rtol=1e-12, atol=1e-12)
    # The normalised latent variance: at most the signal variance, about zero on a training
    # input (noise 1e-8), the whole signal variance far from every training input.
    X = models.training_arrays(name, training).X
    sigma = float(built.hyper.variance)
    _, var_train = built.model.predict(X[:5])
    _, var_far = built.model.predict(np.array([[3.0] * 8, [-3.0] * 8]))
    assert np.all(np.asarray(var) <= sigma)
    if name != "gpg_pic":  # PIC sees another bin's training point through the inducing points
        assert np.all(np.asarray(var_train) < 1e-6 * sigma)
    np.testing.assert_allclose(var_far, sigma, rtol=1e-6)
    assert built.model.nbytes() > 0
    partitioned = models.SPECS[name].partitioned
    want = {"hyper_s", "fit_s"} | ({"partition_s"} if partitioned else set())
    assert set(built.timings) == want and built.timings["hyper_s"] == 0.0  # no fit
    if partitioned and name != "gpg_pic":
        # Every bin holds fewer than ⌈budget·N⌉ anchors, so each near set is exactly that size.
        n = X.shape[0]
        k = math.ceil(FAST["near"]["budget"] * n)
        assert all(a.size < k for a in built.near.anchors)
        assert all(nb.size == k for nb in built.near.near)
        np.testing.assert_array_equal(built.near.fraction, k / n)


def test_exact_models_interpolate(training):
    for name in ("gpg", "gp"):
        cfg = {"hyper": {"fit": False, "lengthscale": 1.0, "noise": 1e-10}}
        m, _ = models.build(name, training, models.restrict(name, cfg)).model.predict(
            training.X[:5]
        )
        np.testing.assert_allclose(m, training.Y[:5], atol=1e-3)


def test_hyperparameter_fit_reports(training):
    built = models.build("gpg", training, {"hyper": {"subset": 30, "max_steps": 300}})
    assert built.hyper_fit.converged, built.hyper_fit.message
    assert built.hyper_fit.noise_fitted and built.hyper_fit.noise_ratio >= 1e-6
    assert built.hyper_fit is not None and built.hyper_fit.subset.size == 30
    assert set(built.timings) == {"hyper_s", "fit_s"} and built.timings["hyper_s"] > 0


def test_unknown_names_and_keys(training):
    with pytest.raises(ValueError, match=r"unknown model 'gps_2x'; valid: \['gp', 'gpg', 'gps_1x'"):
        models.build("gps_2x", training)
    with pytest.raises(ValueError, match=r"unknown key 'bins'"):
        models.build("gpgs", training, {"bins": 4})
    with pytest.raises(ValueError, match=r"unknown key hyper.'sigma'"):
        models.build("gpgs", training, {"hyper": {"sigma": 1.0}})
    with pytest.raises(ValueError, match=r"unknown mean form"):
        models.build(
            "gpgs_schur", training, models.restrict("gpgs_schur", {**FAST, "mean": "median"})
        )


def test_missing_data_is_named(training):
    from dataclasses import replace

    no_grad = replace(training, dY=None)
    with pytest.raises(
        ValueError, match=r"model 'gpgs_schur' needs gradients, which the dataset lacks"
    ):
        models.build("gpgs_schur", no_grad, models.restrict("gpgs_schur", FAST))
    no_raw = replace(training, X_raw=None, Y_raw=None)
    with pytest.raises(ValueError, match=r"model 'gps_8x' trains on the raw 8X samples"):
        models.build("gps_8x", no_raw, models.restrict("gps_8x", FAST))


def test_predict_traces_once(training, caplog):
    model = models.build("gpgs_schur", training, models.restrict("gpgs_schur", FAST)).model
    model.predict(training.X[:4])
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        for s in (0.1, 0.2, 0.3):
            model.predict(training.X[:4] * s)
    assert not [r for r in caplog.records if "Compiling jit(_batch)" in r.getMessage()]


def test_kdtree_and_paper_mean_options(training):
    cfg = {**FAST, "partition": {"scheme": "kdtree", "bins": 4}, "mean": "paper", "route": "direct"}
    built = models.build("gpgs_schur", training, models.restrict("gpgs_schur", cfg))
    assert built.model.partition.scheme == "kdtree" and built.config.mean == "paper"
    # The direct route (a factorisation of K̄_ff per bin) and the global one (one of K̄) give
    # the same predictor.
    ref = models.build(
        "gpgs_schur", training, models.restrict("gpgs_schur", {**cfg, "route": "global"})
    )
    Xq = np.concatenate([training.X[:7] * 0.9, np.random.default_rng(0).uniform(-1, 1, (20, 8))])
    m, v = built.model.predict(Xq)
    rm, rv = ref.model.predict(Xq)
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(v))
    np.testing.assert_allclose(m, rm, rtol=1e-8, atol=1e-8 * np.abs(rm).max())
    np.testing.assert_allclose(v, rv, rtol=1e-8, atol=1e-8 * float(ref.hyper.variance))


def test_hybrid_mean_is_exact_and_variance_an_upper_bound(training):
    """GP-G-S-Hybrid: ExactGP's mean to 1e-10, the dense near-set variance of the query's bin,
    and never below the exact GP-G variance."""
    from gpg.gp import kernels, stack_targets

    cfg = {**FAST, "hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-3}}
    hyb = models.build(
        "gpgs_hybrid",
        training,
        models.restrict("gpgs_hybrid", {**cfg, "variance_dtype": "float64"}),
    )
    ref = models.build("gpg", training, models.restrict("gpg", cfg), hyper=hyb.hyper).model
    Xq = np.random.default_rng(4).uniform(-1, 1, (25, 8))
    m, v = hyb.model.predict_unclipped(Xq)
    me, ve = ref.predict_unclipped(Xq)
    np.testing.assert_allclose(m, me, rtol=1e-10, atol=1e-10 * np.abs(me).max())
    assert np.all(np.asarray(v) >= np.asarray(ve) - 1e-10)
    # Dense near-set formula σ − k_qnᵀ K̄_nn⁻¹ k_qn in NumPy, bin by bin.
    h, X, dims = hyb.hyper, training.X, GRAD_DIMS
    bins = np.asarray(hyb.model.partition.lookup_batch(Xq))
    for q, b in enumerate(bins):
        Xn = X[hyb.near.near[b]]
        K = np.array(kernels.gram(Xn, Xn, h.variance, h.lengthscale, dims, dims))
        K += np.diag(np.asarray(h.noise_diagonal(Xn.shape[0], len(dims))))
        k = np.asarray(kernels.gram(Xq[q : q + 1], Xn, h.variance, h.lengthscale, (), dims))[0]
        want = float(h.variance) - k @ np.linalg.solve(K, k)
        np.testing.assert_allclose(v[q], want, rtol=1e-8, atol=1e-10)
    assert float(hyb.model.noise) == pytest.approx(1e-3)
    del stack_targets


def test_hybrid_float32_variance_factor(training):
    cfg = {**FAST, "hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-3}}
    f64 = models.build(
        "gpgs_hybrid",
        training,
        models.restrict("gpgs_hybrid", {**cfg, "variance_dtype": "float64"}),
    ).model
    f32 = models.build(
        "gpgs_hybrid",
        training,
        models.restrict("gpgs_hybrid", {**cfg, "variance_dtype": "float32"}),
    ).model
    assert f32.nbytes() < f64.nbytes()
    Xq = np.random.default_rng(5).uniform(-1, 1, (20, 8))
    (m64, v64), (m32, v32) = f64.predict(Xq), f32.predict(Xq)
    np.testing.assert_array_equal(m32, m64)  # the mean does not touch the factor
    np.testing.assert_allclose(v32, v64, rtol=1e-4, atol=1e-6)


def test_bad_sizes_fail_before_training(training):
    with pytest.raises(ValueError, match="inducing.points must be a positive integer"):
        models.build(
            "gpg_pic", training, models.restrict("gpg_pic", {**FAST, "inducing": {"points": 0}})
        )
    with pytest.raises(ValueError, match="more inducing points than the 40 training points"):
        models.build(
            "gpg_pic", training, models.restrict("gpg_pic", {**FAST, "inducing": {"points": 41}})
        )
    with pytest.raises(ValueError, match="partition.bins=50 exceeds the 40 training points"):
        models.build("gpgs", training, models.restrict("gpgs", {**FAST, "partition": {"bins": 50}}))
    with pytest.raises(ValueError, match="variance_dtype must be one of"):
        models.build(
            "gpgs", training, models.restrict("gpgs", {**FAST, "variance_dtype": "float16"})
        )


def test_memory_is_checked_before_training(training, monkeypatch):
    from gpg.linalg import memory

    monkeypatch.setattr(memory, "available_bytes", lambda: 1000)
    fitted = []
    monkeypatch.setattr(models, "fit_hyperparameters", lambda *a, **k: fitted.append(1))
    with pytest.raises(memory.InsufficientMemory, match="model 'gpg' on 40 points"):
        models.build("gpg", training, {"hyper": {"subset": 10}})
    assert not fitted


def test_lengthscale_scale(training):
    base = models.build("gpgs", training, models.restrict("gpgs", FAST))
    half = models.build(
        "gpgs",
        training,
        models.restrict("gpgs", {**FAST, "hyper": {**FAST["hyper"], "lengthscale_scale": 0.5}}),
    )
    np.testing.assert_allclose(half.hyper.lengthscale, 0.5 * np.asarray(base.hyper.lengthscale))


def test_points_per_bin_scales_bins_with_n():
    cfg = models.resolve_config("gpgs_hybrid")
    assert cfg.partition.scheme == "kdtree" and cfg.variance_dtype == "float32"
    assert [cfg.partition.n_bins(n) for n in (40, 1000, 5000)] == [1, 7, 33]
    assert models.resolve_config("gpgs").partition.n_bins(5000) == 10
    with pytest.raises(ValueError, match="partition.points_per_bin must be a positive integer"):
        models.resolve_config("gpgs", {"partition": {"points_per_bin": 0}})


def test_train_is_prepare_then_build_and_shares_one_hyper_fit(monkeypatch):
    """models.train: one path for Surrogate.fit and the comparison; with a cache the models
    on the same points share one likelihood fit (gpgs and gpgs_hybrid here), gps_1x gets its
    own (no gradients)."""
    from gpg.quadrotor.vehicle import load_vehicle

    ds, _ = synthetic_dataset(40)
    simple = simple_model_for(ds, load_vehicle())
    fits = []
    real = models.fit_hyper
    monkeypatch.setattr(models, "fit_hyper", lambda *a, **k: fits.append(a[0]) or real(*a, **k))
    cfg = {**FAST, "hyper": {"subset": 20, "max_steps": 2}}
    cache: dict = {}
    out = {
        n: models.train(n, ds, simple, models.restrict(n, cfg), hyper_cache=cache)
        for n in ("gpgs", "gpgs_hybrid")
    }
    out["gps_1x"] = models.train(
        "gps_1x", ds, simple, models.restrict("gps_1x", cfg), hyper_cache=cache
    )
    assert fits == ["gpgs", "gps_1x"] and len(cache) == 2
    a, b = out["gpgs"][1], out["gpgs_hybrid"][1]
    np.testing.assert_array_equal(a.hyper.lengthscale, b.hyper.lengthscale)
    assert a.timings["hyper_s"] == b.timings["hyper_s"] and a.hyper_fit is b.hyper_fit
    np.testing.assert_array_equal(out["gpgs"][0].X, prepare(ds, simple).X)


def test_degenerate_fits_are_refused(training):
    """A fit never returns a model that answers NaN for finite queries."""
    import equinox as eqx

    with pytest.raises(ValueError, match="lengthscale 1e-300 is too small"):
        models.build("gpg", training, {"hyper": {"fit": False, "lengthscale": 1e-300}})
    with pytest.raises(ValueError, match="at least 2 points"):
        models.build("gpg", training, {"hyper": {"subset": 1}})
    built = models.build("gpgs", training, models.restrict("gpgs", FAST))
    broken = eqx.tree_at(lambda m: m.coef, built.model, built.model.coef.at[0, 0, 0].set(np.nan))
    with pytest.raises(ValueError, match=r"model 'gpgs': the fit produced NaN or inf in \.coef"):
        models.check_finite_model("gpgs", broken)


def test_hybrid_mean_by_conjugate_gradients_equals_the_cholesky_one(training):
    """solver.method=cg (matrix-free products, Nyström-preconditioned CG) gives the hybrid the
    Cholesky model's α to its tolerance: the same predictions, the same variances (they come
    from the near sets either way), and a record of the solve."""
    cfg = {
        "hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-3},
        "variance_dtype": "float64",
    }
    chol = models.build("gpgs_hybrid", training, {**cfg, "solver": {"method": "cholesky"}})
    solver = {"method": "cg", "tol": 1e-10, "points": 10, "tile": 16}
    cg = models.build("gpgs_hybrid", training, {**cfg, "solver": solver})
    Xq = training.X[:9] * 0.95
    (m1, v1), (m2, v2) = chol.model.predict(Xq), cg.model.predict(Xq)
    np.testing.assert_allclose(m2, m1, rtol=0, atol=1e-7 * float(np.abs(m1).max()))
    np.testing.assert_array_equal(v2, v1)
    d = cg.diagnostics
    assert d["solver"] == "cg" and max(d["cg_residual"]) <= 1e-10 and d["cg_iterations"] > 0
    assert chol.diagnostics == {}


def test_solver_auto_picks_cg_when_the_dense_matrix_does_not_fit(monkeypatch):
    """The memory check before training accounts for the CG path: at data=large's size the
    dense K̄ (205 GB) is refused, while auto (and cg) ask for a few GB."""
    from gpg.kinds import hybrid
    from gpg.linalg import memory

    monkeypatch.setattr(memory, "available_bytes", lambda: 24 * 2**30)
    n, g = 20000, 7
    auto = models.resolve_config("gpgs_hybrid")
    dense = models.resolve_config("gpgs_hybrid", {"solver": {"method": "cholesky"}})
    assert hybrid.solver_method(auto, n, g) == "cg"
    assert models.required_bytes("gpgs_hybrid", dense, n, g) > 200e9
    assert models.required_bytes("gpgs_hybrid", auto, n, g) < 8 * 2**30
    assert hybrid.solver_method(auto, 1000, g) == "cholesky"
    with pytest.raises(ValueError, match="model 'gpg' does not read option 'solver.method'"):
        models.resolve_config("gpg", {"solver": {"method": "cg"}})
    with pytest.raises(ValueError, match="solver.method must be one of"):
        models.resolve_config("gpgs_hybrid", {"solver": {"method": "lu"}})


def test_full_hyper_refits_on_every_point_from_the_subset_fit(training):
    """hyper.full: the dense fit on the subset, then the stochastic likelihood on all points
    starting there; it ends no worse (by the dense likelihood on all points) than it began."""
    from gpg.gp.gram import log_marginal_likelihood, stack_targets

    cfg = {"hyper": {"fit": True, "subset": 15, "max_steps": 30, "full": True,
                     "full_max_steps": 3, "probes": 10}}  # fmt: skip
    sub = {"hyper": {**cfg["hyper"], "full": False}}
    hyper, res, _ = models.fit_hyper("gpg", training, cfg)
    start, _, _ = models.fit_hyper("gpg", training, sub)
    n = training.X.shape[0]
    assert res.subset.size == n and res.noise_fitted

    def nll(h):
        arrays = models.training_arrays("gpg", training)
        Ybar = stack_targets(jnp.asarray(arrays.Y), jnp.asarray(arrays.dY))
        return -float(log_marginal_likelihood(jnp.asarray(arrays.X), Ybar, h, arrays.dims))

    assert nll(hyper) <= nll(start) + 1e-6 * abs(nll(start))
