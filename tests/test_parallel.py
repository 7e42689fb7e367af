"""gpg.parallel: bins and query blocks spread over JAX devices give the single-device results.

Several devices need ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` before JAX starts,
so those checks run in a fresh interpreter; the rest runs on this process's one device.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from gpg import parallel
from gpg.gp import local, partition, pic
from gpg.gp.gram import stack_targets
from gpg.gp.hyper import Hyper

ROOT = Path(__file__).resolve().parents[1]


def problem(seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (90, 3))
    Y = np.stack([np.sin(3 * X[:, 0]) * X[:, 1], X[:, 2] ** 2], 1)
    dY = rng.normal(size=(90, 2, 2))
    h = Hyper(variance=1.3, lengthscale=np.array([0.7, 0.9, 1.1]), noise=1e-4, grad_noise=1e-3)
    part = partition.build(X, "slab", 5, dim=0)
    near = partition.near_sets(X, part, h.lengthscale, budget=0.3)
    return X, stack_targets(Y, dY), h, near


def test_jax_local_precompute_matches_the_lapack_path():
    X, Ybar, h, near = problem()
    ref = local.precompute(X, Ybar, h, (0, 1), near)
    got = local.precompute(X, Ybar, h, (0, 1), near, devices=1)
    assert len(got) == len(ref) == 5
    for a, b in zip(ref, got, strict=True):
        assert b.lower and b.n_rows == a.n_rows
        np.testing.assert_allclose(b.coef, a.coef, rtol=1e-9, atol=1e-9 * np.abs(a.coef).max())
        np.testing.assert_allclose(b.factor, a.factor, rtol=0, atol=1e-9 * np.abs(a.factor).max())
        np.testing.assert_allclose(b.yty, a.yty, rtol=1e-9)


def pic_problem():
    X, Ybar, h, _ = problem()
    part = partition.build(X, "slab", 4, dim=0)
    bins = np.asarray(part.lookup_batch(X))
    blocks = [np.flatnonzero(bins == b) for b in range(4)]
    blocks[1] = blocks[1][:-3]  # unequal blocks: padding is exercised
    blocks[0] = np.sort(np.concatenate([blocks[0], np.flatnonzero(bins == 1)[-3:]]))
    Z = pic.inducing_inputs(X, 12, seed=0)
    return X, Ybar, h, blocks, Z


def test_jax_pic_precompute_matches_the_host_path():
    X, Ybar, h, blocks, Z = pic_problem()
    ref = pic.precompute(X, Ybar, h, (0, 1), blocks, Z)
    got = list(pic.iter_precompute_devices(X, Ybar, h, (0, 1), blocks, Z, devices=1))
    for a, b in zip(ref, got, strict=True):
        assert b.dense_rows == a.dense_rows and not b.lower and b.n_rows == a.n_rows
        np.testing.assert_allclose(b.coef, a.coef, rtol=0, atol=1e-8 * np.abs(a.coef).max())
        # The variance form RᵀR, not R itself (a factor is unique only up to rounding).
        np.testing.assert_allclose(
            b.factor.T @ b.factor,
            a.factor.T @ a.factor,
            rtol=0,
            atol=1e-8 * np.abs(a.factor).max() ** 2,
        )
        np.testing.assert_allclose(b.yty, a.yty, rtol=1e-8)


def test_devices_are_checked():
    n = len(jax.devices())
    assert parallel.devices(None) == jax.devices()[:1]
    with pytest.raises(ValueError, match=rf"devices={n + 1}, but {n} device\(s\) are available"):
        parallel.devices(n + 1)
    with pytest.raises(ValueError, match="devices is an empty list"):
        parallel.devices([])
    with pytest.raises(ValueError, match="devices must be a count or a list"):
        parallel.devices(True)


def test_map_units_keeps_the_order_and_chunks_cover_the_rows():
    units = [(np.full(3, float(i)),) for i in range(7)]
    out = parallel.map_units(jax.jit(lambda s, a: a * s), 2.0, units, parallel.devices(1))
    np.testing.assert_array_equal(np.stack(out)[:, 0], 2.0 * np.arange(7))
    sl = parallel.chunks(10, 4)
    assert [(s.start, s.stop) for s in sl] == [(0, 4), (4, 8), (8, 10)]


PRECOMPUTE_SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 4, jax.devices()
    from tests.test_parallel import pic_problem, problem
    from gpg.gp import local, pic

    X, Ybar, h, near = problem()
    one = local.precompute(X, Ybar, h, (0, 1), near, devices=1)
    four = local.precompute(X, Ybar, h, (0, 1), near, devices=4)
    for a, b in zip(one, four, strict=True):
        assert np.array_equal(a.coef, b.coef) and np.array_equal(a.factor, b.factor)

    X, Ybar, h, blocks, Z = pic_problem()
    p1 = list(pic.iter_precompute_devices(X, Ybar, h, (0, 1), blocks, Z, devices=1))
    p4 = list(pic.iter_precompute_devices(X, Ybar, h, (0, 1), blocks, Z, devices=4))
    for a, b in zip(p1, p4, strict=True):
        assert np.array_equal(a.coef, b.coef) and np.array_equal(a.factor, b.factor)

    from gpg.gp.matfree import gram_matvec_devices
    rng = np.random.default_rng(3)
    V = rng.normal(size=(X.shape[0] * 3, 2))
    m1 = gram_matvec_devices(X, h, (0, 1), V, devices=1, tile=16)
    m4 = gram_matvec_devices(X, h, (0, 1), V, devices=4, tile=16)
    assert np.array_equal(np.asarray(m1), np.asarray(m4))
    print("OK")
    """
)

SURROGATE_SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 4, jax.devices()
    from tests.helpers import synthetic_dataset
    from gpg import Surrogate

    data, _ = synthetic_dataset(60, seed=3)
    cfg = {"hyper": {"fit": False}, "partition": {"bins": 6}}
    s1 = Surrogate.fit(data, "gpgs", cfg, residual=False, devices=1)
    s4 = Surrogate.fit(data, "gpgs", cfg, residual=False, devices=4)
    for a, b in zip(jax.tree.leaves(s1), jax.tree.leaves(s4), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))

    rng = np.random.default_rng(0)
    n = 1000  # four blocks of 256 (the last one padded)
    rpm = rng.uniform(2000, 5000, (n, 4))
    euler = rng.uniform(-0.4, 0.4, (n, 3))
    v = rng.uniform(-8, 8, (n, 3))
    ref = s1.predict_batch(rpm, euler, v, chunk=256)
    r1 = s1.replicate(1).predict_batch(rpm, euler, v, chunk=256)
    r4 = s1.replicate(4).predict_batch(rpm, euler, v, chunk=256)
    m4 = s1.replicate(4).predict_batch(rpm, euler, v, chunk=256, mean_only=True)
    for f in ("force", "torque", "levels", "variance", "in_domain"):
        a, b = np.asarray(getattr(r1, f)), np.asarray(getattr(r4, f))
        assert a.shape[0] == n and np.array_equal(a, b), f
        np.testing.assert_allclose(b, np.asarray(getattr(ref, f)), rtol=1e-12, atol=1e-12)
    assert np.array_equal(m4.force, r4.force) and m4.variance is None
    print("OK")
    """
)


def subprocess_env(devices: int | None = None) -> dict[str, str]:
    """This process's environment for a child JAX: the same XLA flags (a bit-for-bit comparison
    with this process needs the same compiler configuration, `make test-xla`'s too), with
    ``devices`` virtual CPU devices instead of any device count set here."""
    flags = [
        f
        for f in os.environ.get("XLA_FLAGS", "").split()
        if not f.startswith("--xla_force_host_platform_device_count")
    ]
    if devices is not None:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    return {
        **os.environ,
        "XLA_FLAGS": " ".join(flags),
        "JAX_PLATFORMS": "cpu",
        "PYTHONPATH": str(ROOT),
    }


def four_devices(script: str) -> None:
    env = subprocess_env(4)
    p = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.strip().endswith("OK")


def test_four_devices_give_the_single_device_precompute_bit_for_bit():
    four_devices(PRECOMPUTE_SCRIPT)


@pytest.mark.slow
def test_four_devices_give_the_single_device_surrogate_and_predictions_bit_for_bit():
    four_devices(SURROGATE_SCRIPT)


HOST_SCRIPT = textwrap.dedent(
    """
    import sys, jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from gpg import parallel
    parallel.initialize(
        coordinator_address=sys.argv[1], num_processes=2, process_id=int(sys.argv[2])
    )
    assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
    from tests.test_parallel import problem
    from gpg.gp import local
    X, Ybar, h, near = problem()
    got = local.precompute(X, Ybar, h, (0, 1), near, devices=2)
    flat = [f.factor.ravel() for f in got] + [f.coef.ravel() for f in got]
    from gpg.gp.matfree import gram_matvec_devices
    V = np.random.default_rng(1).normal(size=(Ybar.shape[0], 3))
    flat.append(np.asarray(gram_matvec_devices(X, h, (0, 1), V, devices=2, tile=16)).ravel())
    np.save(sys.argv[3], np.concatenate(flat))
    """
)


# Two subprocesses (a stress run of the multi-host path): slow; the fast set keeps the same
# units over four devices in one process (test_four_devices_give_...).
@pytest.mark.slow
def test_two_processes_share_the_bins_and_both_hold_every_result(tmp_path):
    """Two processes on this machine stand for two hosts (jax.distributed with gloo on CPU):
    each computes the bins of its own device, and the row tiles of its share of a
    matrix-free product ``K̄ V``; both end with all bins and the whole product, bit for bit
    the one-device results."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = subprocess_env()
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                HOST_SCRIPT,
                f"127.0.0.1:{port}",
                str(i),
                str(tmp_path / f"{i}.npy"),
            ],
            cwd=ROOT,
            env=env,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-3000:]
    X, Ybar, h, near = problem()
    ref = local.precompute(X, Ybar, h, (0, 1), near, devices=1)
    from gpg.gp.matfree import gram_matvec_devices

    V = np.random.default_rng(1).normal(size=(Ybar.shape[0], 3))
    product = np.asarray(gram_matvec_devices(X, h, (0, 1), V, devices=1, tile=16)).ravel()
    want = np.concatenate(
        [f.factor.ravel() for f in ref] + [f.coef.ravel() for f in ref] + [product]
    )
    for i in range(2):
        np.testing.assert_array_equal(np.load(tmp_path / f"{i}.npy"), want)
