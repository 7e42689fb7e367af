"""gpg.design: conditioning a surrogate, the acquisition against a dense NumPy computation,
its properties, and the bad inputs (one clear message, the surrogate unchanged)."""

from dataclasses import asdict, replace

import jax.numpy as jnp
import numpy as np
import pytest

from gpg import design
from gpg.data.bounds import Bounds
from gpg.design.acquisition import propose as propose_rows
from gpg.design.acquisition import subsets
from gpg.gp import kernels
from gpg.gp.exact import ExactGP
from gpg.gp.hyper import Hyper
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset

CFG = {"hyper": {"fit": False, "lengthscale": 0.8}}
BOX = asdict(Bounds())  # the synthetic data's sampling box (it records none)
HYB = {**CFG, "partition": {"bins": 3, "points_per_bin": None},
       "near": {"budget": 0.5, "points": None}, "variance_dtype": "float64"}  # fmt: skip


@pytest.fixture(scope="module")
def data():
    full, _ = synthetic_dataset(48, seed=3, raw=False)
    return full.subset(np.arange(40)), full.subset(np.arange(40, 48))


@pytest.mark.parametrize(("name", "cfg"), [("gpg", CFG), ("gpgs_hybrid", HYB)])
def test_surrogate_condition_equals_a_refit(data, name, cfg):
    """New cases, some lacking some gradients (NaN), conditioned: equal to a rebuild with the
    same hyperparameters to 1e-8 of the normalised mean and variance (measured 2e-14)."""
    old, new = data
    jac, jn = new.jac_aero.copy(), new.jac_noise.copy()
    jac[::2, :, 3], jn[::2, :, 3] = np.nan, np.nan
    new = replace(new, jac_aero=jac, jac_noise=jn)
    sur = Surrogate.fit(old, name, cfg, bounds=BOX)
    grown = sur.condition(new)
    both = design.merge_datasets(old, new)
    ref = design.rebuild(sur, both)
    Q = np.asarray(sur.normalizer.x(synthetic_dataset(30, seed=7, raw=False)[0].x))
    (m1, v1), (m2, v2) = grown.model.predict(Q), ref.predict(Q)
    np.testing.assert_allclose(m1, m2, atol=1e-8)
    np.testing.assert_allclose(v1, v2, atol=1e-8)
    assert sur.model is not grown.model  # the surrogate itself is unchanged


def test_kinds_that_cannot_condition_refuse_by_their_kind(data):
    """A kind without conditioning refuses ``condition``, ``cases`` and the acquisition with
    one message naming the kinds that can; design reads models only through their kind."""
    old, new = data
    sur = Surrogate.fit(old, "gpg_pic", {**CFG, "inducing": {"points": 8}}, bounds=BOX)
    for call in (lambda: sur.condition(new), lambda: design.training_cases(sur),
                 lambda: design.propose(sur, old, 2, candidates=20, reference=10)):  # fmt: skip
        with pytest.raises(ValueError, match="kind 'pic' cannot be conditioned.*gpg and gpgs_hy"):
            call()


def test_bad_new_cases_leave_the_surrogate_unchanged(data):
    old, new = data
    sur = Surrogate.fit(old, "gpg", CFG, bounds=BOX)
    before = np.asarray(sur.model.alpha).copy()
    with pytest.raises(ValueError, match="outputs"):
        sur.condition(new.without("noise"))
    deg = replace(new, x=np.c_[new.x[:, :4], np.degrees(new.x[:, 4:7]), new.x[:, 7:]])
    with pytest.raises(ValueError, match="outside the surrogate's input box.*units"):
        sur.condition(deg)
    with pytest.raises(ValueError, match="duplicate training cases"):
        sur.condition(old.subset(np.arange(2)))
    with pytest.raises(ValueError, match="duplicate one another"):
        sur.condition(new.subset(np.array([0, 0])))
    with pytest.raises(ValueError, match="gpg.data.Dataset"):
        sur.condition(new.x)
    with pytest.raises(ValueError, match="NaN"):
        replace(new, y_aero=np.where(np.arange(6) == 0, np.nan, new.y_aero))
    with pytest.raises(ValueError, match="NaN for some outputs but not others"):
        jac = new.jac_aero.copy()
        jac[0, 0, 0] = np.nan
        replace(new, jac_aero=jac)
    np.testing.assert_array_equal(np.asarray(sur.model.alpha), before)


H = Hyper(variance=1.0, lengthscale=np.array([0.7, 0.8, 0.9]), noise=1e-3,
          grad_noise=np.array([1e-3, 2e-3]))  # fmt: skip
DIMS = (0, 2)


def _gp(n=12, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 3))
    return ExactGP.fit(X, np.sin(X.sum(1))[:, None], rng.normal(size=(n, 1, 2)),
                       grad_dims=DIMS, hyper=H)  # fmt: skip


def _dense_integrated_variance(X, rows, Z):
    """Mean posterior latent variance over Z, conditioned on ``rows`` (a mask over the
    dimension-major stacked rows of X), by dense NumPy."""
    K = np.asarray(kernels.gram(X, X, 1.0, H.lengthscale, DIMS, DIMS))
    n = X.shape[0]
    noise = np.r_[np.full(n, 1e-3), np.full(n, 1e-3), np.full(n, 2e-3)]
    Kn = (K + np.diag(noise))[np.ix_(rows, rows)]
    kz = np.asarray(kernels.gram(Z, X, 1.0, H.lengthscale, (), DIMS))[:, rows]
    return np.mean(1.0 - np.einsum("zi,ij,zj->z", kz, np.linalg.inv(Kn), kz))


@pytest.mark.parametrize("gradients", ["all", "none", "choose"])
def test_gain_of_one_case_matches_dense_numpy(gradients):
    gp = _gp()
    rng = np.random.default_rng(1)
    cand, Z = rng.uniform(-1, 1, (25, 3)), rng.uniform(-1, 1, (30, 3))
    b = propose_rows(gp, cand, Z, 1, gradients=gradients)
    X = np.asarray(gp.X)
    X1 = np.r_[X, cand[b.index]]
    n1 = X1.shape[0]
    rows = np.ones(3 * n1, bool)
    rows[[n1 - 1 + n1, n1 - 1 + 2 * n1]] = b.gradients[0]
    before = _dense_integrated_variance(X, np.ones(3 * X.shape[0], bool), Z)
    after = _dense_integrated_variance(X1, rows, Z)
    assert b.gain[0] == pytest.approx(before - after, rel=1e-8)
    assert b.cost[0] == 1 + b.gradients[0].sum()
    if gradients == "all":
        assert b.gradients.all()
    if gradients == "none":
        assert not b.gradients.any()


def test_choose_is_the_best_gain_per_run_over_every_subset():
    """``choose`` scores every subset of every kept candidate: its pick is worth at least as
    much per run as any candidate with all its gradients or with none."""
    gp = _gp()
    rng = np.random.default_rng(2)
    cand, Z = rng.uniform(-1, 1, (10, 3)), rng.uniform(-1, 1, (30, 3))
    best = propose_rows(gp, cand, Z, 1, gradients="choose", keep=10)
    for fixed in ("all", "none"):
        other = propose_rows(gp, cand, Z, 1, gradients=fixed, keep=10)
        assert other.gain[0] / other.cost[0] <= best.gain[0] / best.cost[0] + 1e-12
    assert subsets(2, "choose").shape == (4, 3)  # value row always, 2² gradient subsets


def test_a_case_already_in_the_data_scores_no_higher():
    gp = _gp()
    rng = np.random.default_rng(3)
    cand, Z = rng.uniform(-1, 1, (8, 3)), rng.uniform(-1, 1, (30, 3))
    first = propose_rows(gp, cand, Z, 8, gradients="all", keep=8)
    gain = dict(zip(first.index.tolist(), first.gain.tolist(), strict=True))
    c = int(first.index[0])
    grown = gp.condition(cand[c : c + 1], np.zeros((1, 1)), np.zeros((1, 1, 2)))
    again = propose_rows(grown, cand, Z, 8, gradients="all", keep=8)
    for i, g in zip(again.index.tolist(), again.gain.tolist(), strict=True):
        if i == c:
            # a repeat of a noisy case still adds a little (measured 0.2 % of its first gain)
            assert g <= 0.01 * gain[c]
    # greedy gains fall: each pick is worth no more than the one before it
    assert np.all(np.diff(first.gain / first.cost) <= 1e-12)


def test_a_covariance_block_indefinite_by_rounding_is_clipped_and_beyond_it_refused():
    """``Σ = K − VVᵀ`` near the data is a difference of nearly equal numbers: a block that
    rounding leaves indefinite by more than the noise is clipped to the nearest PSD block
    (same eigenvectors), a PSD block is left as it is, and a block indefinite beyond rounding
    (a stored factor that does not match ``K̄``) is an error, not a pick."""
    from gpg.design.acquisition import _greedy, _psd

    rng = np.random.default_rng(4)
    U = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    A = (U * np.array([2.0, 0.5, -1e-8])) @ U.T  # one eigenvalue below -noise
    np.testing.assert_allclose(_psd(A), (U * np.array([2.0, 0.5, 0.0])) @ U.T, atol=1e-14)
    B = (U * np.array([2.0, 0.5, 1e-3])) @ U.T
    np.testing.assert_allclose(_psd(B), B, atol=1e-14)
    # One candidate with rows (value, two gradients), its block indefinite: the pick conditions.
    S_tz = rng.normal(size=(3, 5))
    noise = np.array([1e-9, 1e-9, 1e-9])
    masks = subsets(2, "all")
    picked, sub, gains = _greedy(A.copy(), S_tz, np.full(5, 0.2), masks, noise, 1)
    assert picked.tolist() == [0] and np.isfinite(gains).all()
    wrong = (U * np.array([2.0, 0.5, -0.3])) @ U.T
    with pytest.raises(RuntimeError, match="stored factor does not match"):
        _greedy(wrong, S_tz, np.full(5, 0.2), masks, noise, 1)


def test_propose_on_a_surrogate_and_bad_candidates(data):
    old, _ = data
    # hyper.max_steps bounds the weighted outputs' own fit (the surrogate's is fixed)
    sur = Surrogate.fit(old, "gpg", {"hyper": {**CFG["hyper"], "max_steps": 5}}, bounds=BOX)
    p = design.propose(sur, old, 3, candidates=200, reference=64, seed=0)
    assert p.x.shape == (3, 8) and p.gradients.shape == (3, 7)
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    assert np.all((p.x >= lo) & (p.x <= hi))
    outside = np.r_[p.x[:1] + 0.0, p.x[:1] + 0.0]
    outside[0, 7] = hi[7] + 5.0
    with pytest.raises(ValueError, match="outside the surrogate's input box"):
        design.propose(sur, old, 1, candidates=outside, reference=16)
    with pytest.raises(ValueError, match="gradients must be one of"):
        design.propose(sur, old, 1, candidates=20, gradients="some")
    # the sizes above: their compiled programs serve this call too
    w = design.propose(sur, old, 2, candidates=200, reference=64, weights={"L1": 1.0, "L2": 1.0})
    assert w.x.shape == (2, 8)
    with pytest.raises(ValueError, match="unknown outputs"):
        design.propose(sur, old, 1, candidates=20, weights={"Q": 1.0})
    assert jnp.all(jnp.isfinite(sur.model.mean.coef))


def test_a_conditioned_surrogate_checkpoints_and_conditions_again(data, tmp_path):
    """Saved after one conditioning and loaded, it conditions on the next cases as the
    unsaved one conditions on both at once (the factor's row order survives the file)."""
    from gpg import checkpoint

    old, new = data
    sur = Surrogate.fit(old, "gpgs_hybrid", HYB, bounds=BOX)
    path = checkpoint.save(tmp_path / "sur", sur.condition(new.subset(np.arange(4))))
    again = checkpoint.load(path).condition(new.subset(np.arange(4, 8)))
    once = sur.condition(new)
    Q = np.asarray(sur.normalizer.x(synthetic_dataset(10, seed=8, raw=False)[0].x))
    np.testing.assert_allclose(again.model.predict(Q)[0], once.model.predict(Q)[0], atol=1e-12)
    exact = Surrogate.fit(old, "gpg", CFG, bounds=BOX).condition(new.subset(np.arange(3)))
    loaded = checkpoint.load(checkpoint.save(tmp_path / "exact", exact))
    np.testing.assert_array_equal(np.asarray(loaded.model.order), np.asarray(exact.model.order))
