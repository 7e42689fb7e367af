"""Dense solves on the device (gpg.linalg.device), run here on the CPU device: the placement
rule, the factorisation and its error, the device Gram against the host one, and every kind
built with ``solver.device=device`` against the same build on the host."""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import models
from gpg.gp.exact import ExactGP
from gpg.gp.gram import assemble_gram, assemble_rows_gram, device_gram
from gpg.gp.hyper import Hyper
from gpg.linalg import device
from gpg.linalg.dense import NotPositiveDefiniteError
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset

EPS = np.finfo(np.float64).eps


class _FakeGPU:
    platform = "gpu"

    def __init__(self, free):
        self.free = free

    def memory_stats(self):
        return {"bytes_limit": self.free + 100, "bytes_in_use": 100}

    def __str__(self):
        return "cuda:0 (fake)"


def test_place_rule(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="gpg")
    assert device.place("host", 10**15, "K̄") == "host"
    assert device.place("device", 10**15, "K̄") == "device"  # obeyed, even past any memory
    assert device.place("auto", 10, "K̄") == "host"  # the CPU backend: LAPACK in place
    assert "no accelerator" in caplog.text
    with pytest.raises(ValueError, match="solver.device"):
        device.place("gpu", 10, "K̄")
    monkeypatch.setattr(device, "accelerator", lambda: _FakeGPU(free=10**9))
    assert device.place("auto", int(10**9 / device.HEADROOM) - 10, "K̄") == "device"
    assert device.place("auto", int(10**9 / device.HEADROOM) + 10, "K̄") == "host"
    assert "do not fit" in caplog.text


def test_cholesky_refuses_a_matrix_that_is_not_positive_definite():
    K = np.eye(5)
    K[3, 3] = -1.0
    with pytest.raises(NotPositiveDefiniteError, match="not numerically positive definite"):
        device.cholesky(jnp.asarray(K), what="K̄")


def test_factor_solve_against_numpy(rng):
    A = rng.normal(size=(30, 30))
    K = A @ A.T + 30 * np.eye(30)
    Y = rng.normal(size=(30, 4))
    alpha, logdet, Linv = device.factor_solve(jnp.asarray(K), Y, inverse=True)
    L = np.linalg.cholesky(K)
    cond = np.linalg.cond(K)
    np.testing.assert_allclose(alpha, np.linalg.solve(K, Y), rtol=0, atol=30 * cond * EPS)
    assert abs(logdet - np.sum(np.log(np.diag(L)))) < 30 * 30 * EPS * abs(logdet)
    np.testing.assert_allclose(np.asarray(Linv) @ L, np.eye(30), atol=30 * cond * EPS)


@pytest.mark.parametrize("case", ["plain", "observed", "bases"])
def test_device_gram_and_exact_fit_equal_the_host(rng, case):
    n, dims = 30, (0, 2)
    X = rng.uniform(-1, 1, (n, 3))
    Y = np.sin(X @ rng.normal(size=(3, 2)))
    dY = rng.normal(size=(n, 2, 2))
    h = Hyper(variance=1.3, lengthscale=np.array([0.7, 0.9, 0.6]), noise=1e-3)
    kw = {
        "plain": {},
        "observed": {"observed": rng.random((n, 2)) > 0.3},
        "bases": {"bases": np.linalg.qr(rng.normal(size=(n, 2, 2)))[0]},
    }[case]
    index = None
    if case == "observed":
        obs = kw["observed"]
        index = np.flatnonzero(np.concatenate([np.ones(n, bool), obs.T.ravel()]))
    bases = kw.get("bases")
    if index is None and bases is None:
        host = assemble_gram(X, h, dims)
    else:
        sel = np.arange(3 * n) if index is None else index
        host = assemble_rows_gram(X, sel, h, dims, bases=bases)
    dev = np.asarray(device_gram(X, h, dims, index=index, bases=bases, chunk_bytes=4096))
    np.testing.assert_allclose(dev, host, rtol=0, atol=16 * EPS * np.abs(host).max())

    a = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=h, device="host", **kw)
    b = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=h, device="device", **kw)
    Xq = rng.uniform(-1, 1, (7, 3))
    (ma, va), (mb, vb) = a.predict(Xq), b.predict(Xq)
    # Two factorisations of one K̄ agree to cond(K̄)·eps relative (the noise sets cond).
    tol = np.linalg.cond(host) * EPS * 100
    np.testing.assert_allclose(np.asarray(mb), np.asarray(ma), rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(vb), np.asarray(va), rtol=0, atol=tol)
    assert abs(float(a.log_marginal_likelihood - b.log_marginal_likelihood)) < tol * host.shape[0]
    assert isinstance(b.chol_inv.blocks[0], jax.Array)


FIXED = {"hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-3}, "variance_dtype": "float64"}
BINS = {"partition": {"bins": 3, "points_per_bin": None}}


@pytest.mark.parametrize(
    "name, cfg",
    [
        ("gpgs_hybrid", {**BINS, "near": {"budget": 0.5, "points": None}}),
        ("gpg_pic", {**BINS, "inducing": {"points": 8}}),
    ],
)
def test_every_kind_on_the_device_equals_the_host(name, cfg):
    """The per-bin programs on the device (the hybrid's near sets and its global α, PIC's
    blocks); the exact kind is ExactGP.fit's device path, tested above."""
    data = synthetic_dataset(30, seed=2, raw=False)[0]
    host = Surrogate.fit(data, name, {**FIXED, **cfg, "solver": {"device": "host"}})
    dev = Surrogate.fit(data, name, {**FIXED, **cfg, "solver": {"device": "device"}})
    rng = np.random.default_rng(1)
    states = (rng.uniform(2500, 5000, (8, 4)), rng.uniform(-0.3, 0.3, (8, 3)))
    v = rng.uniform(-4, 4, (8, 3))
    p, q = host.predict_batch(*states, v), dev.predict_batch(*states, v)
    # Normalised noise 1e-3 bounds cond(K̄) by about R/1e-3; a relative 1e-7 is ample room.
    for a, b in ((p.force, q.force), (p.torque, q.torque), (p.variance, q.variance)):
        scale = float(np.abs(np.asarray(a)).max())
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-7 * scale)


def test_solver_device_is_read_by_every_factorising_kind(monkeypatch):
    for name in ("gpg", "gp", "gpgs", "gps_1x", "gpgs_hybrid", "gpg_pic"):
        assert models.resolve_config(name, {"solver": {"device": "host"}}).solver.device == "host"
    with pytest.raises(ValueError, match="solver.method"):
        models.resolve_config("gpg", {"solver": {"method": "cg"}})
    asked = []
    place = device.place
    monkeypatch.setattr(device, "place", lambda mode, *a: asked.append(mode) or place(mode, *a))
    data = synthetic_dataset(12, seed=4, raw=False)[0]
    Surrogate.fit(data, "gpg", {**FIXED, "solver": {"device": "device"}})
    assert asked == ["device"]  # the exact kind passes its setting on
    with pytest.raises(ValueError, match="solver.device"):
        models.resolve_config("gpgs_hybrid", {"solver": {"device": "tpu"}})
