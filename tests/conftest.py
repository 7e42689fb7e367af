"""Shared test set-up: float64 (set here for the whole session: the library leaves it to the
caller), fixed seeds, and the physics fixtures
that are compiled once per session (the generator takes seconds to compile)."""

import gc
import os

# The fast suite is bound by XLA compilation, not by running what it compiles. Two switches
# cut that: JAX's own for this case (little optimisation: a fifth off the suite's CPU time) and
# XLA CPU's older fusion emitters (the MLIR ones compile slower: a third off what is left).
# XLA's threads and the workers' cores are set below. The result is a second configuration
# beside the users' default one (multi-threaded, every core), which `make test-xla` runs
# (GPG_FAST_COMPILE=0, with another instruction set and without YNNPACK): tolerances follow
# from the numerics, not from one configuration's bits, so both pass. Set before JAX is
# imported, in the environment, so that the tests' subprocesses inherit it.
if os.environ.get("GPG_FAST_COMPILE", "1") != "0":
    os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
    flags = os.environ.get("XLA_FLAGS", "")
    # The workers already fill the cores, so XLA's own threads (a program's LLVM module cut
    # into 32 parts compiled on a pool, Eigen's products on several threads) have none to
    # gain: one part and one-thread Eigen took a few percent off the suite (docs/install.md).
    for flag in ("xla_cpu_use_fusion_emitters=false", "xla_cpu_parallel_codegen_split_count=1",
                 "xla_cpu_multi_thread_eigen=false"):  # fmt: skip
        if flag.split("=")[0] not in flags:
            flags = f"{flags} --{flag}".strip()
    os.environ["XLA_FLAGS"] = flags
    # Each pytest-xdist worker on its own share of the cores (one each on two), before JAX
    # sizes its thread pools from the cores it may use: on two cores, two workers each with
    # pools of two threads took an eighth to a sixth more CPU time than one worker a core
    # (docs/install.md). The tests' subprocesses inherit the share.
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if worker and workers and hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) >= int(workers):
            os.sched_setaffinity(0, set(cpus[int(worker.removeprefix("gw")) :: int(workers)]))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gpg.quadrotor import bemt  # noqa: E402
from gpg.quadrotor.frames import R_WB  # noqa: E402
from gpg.quadrotor.generator import Generator, evaluate, jacobian  # noqa: E402
from gpg.quadrotor.simple_model import fit_to_generator  # noqa: E402
from gpg.quadrotor.vehicle import load_vehicle  # noqa: E402

jax.config.update("jax_enable_x64", True)  # before any test builds an array


def pytest_configure(config):
    """One persistent XLA compilation cache for the run, shared by the pytest-xdist workers:
    the suite is bound by compiling the same programs (generator, kernels) in each worker, and
    in one worker the same program traced from two functions (two fixtures' surrogates). Every
    program over 0.02 s is kept: at 0.5 s the suite took a few percent more CPU time than at
    0.1 s, and at 0.02 s 284 and 303 s of pytest in two runs against 301-308 s in four at
    0.1 s (with the collector's passes below; the machine's own spread is some 20 s)."""
    import tempfile
    from pathlib import Path

    run = os.environ.get("PYTEST_XDIST_TESTRUNUID", "single")
    cache = Path(tempfile.gettempdir()) / f"gpg-test-xla-cache-{run}"
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.02)


def pytest_collection_finish(session):
    """The objects alive once every test module is imported (jax, scipy, the fixtures'
    modules) are left out of the cyclic collector's full passes from here on: each worker's
    heap grows to millions of objects (traced programs, compiled executables' caches), and the
    full passes over it took about 7 % of the suite's CPU time (41 s of 612, gc's callbacks
    timed; 17 s with these freezes)."""
    gc.freeze()


def pytest_runtest_teardown(item, nextitem):
    """The same at every test module's end: what a module left alive stays (about 5.5 GB of
    peak memory a worker); its cyclic garbage is not reclaimed, for a full pass less each time."""
    if nextitem is None or nextitem.module is not item.module:
        gc.freeze()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def vehicle():
    return load_vehicle("sui_endurance")


@pytest.fixture(scope="session")
def gen(vehicle):
    return Generator(vehicle)


@pytest.fixture(scope="session")
def simple(gen):
    """M fitted to the generator's hover sweep (compiles the sweep once per session)."""
    return fit_to_generator(gen)


@pytest.fixture(scope="session")
def aero(gen):
    """``aero(rpm, euler, V)`` -> AeroResult in the dataset frame (airflow along +x)."""
    f = jax.jit(
        lambda rpm, euler, V: bemt.aero(
            gen.vehicle, gen.bemt, rpm, R_WB(euler), jnp.stack([V, 0.0, 0.0])
        )
    )
    return lambda rpm, euler, V: f(
        jnp.asarray(rpm, float), jnp.asarray(euler, float), jnp.asarray(V, float)
    )


@pytest.fixture(scope="session")
def y_of(gen):
    f = jax.jit(lambda x: evaluate(gen, x))
    return lambda x: f(jnp.asarray(x, float))


@pytest.fixture(scope="session")
def y_body_of(gen):
    """The body-frame generator ``y_B(x_B)``, compiled once per session."""
    from gpg.quadrotor.generator import evaluate_body

    f = jax.jit(lambda x: evaluate_body(gen, x))
    return lambda x: f(jnp.asarray(x, float))


@pytest.fixture(scope="session")
def jac_of(gen):
    f = jax.jit(lambda x: jacobian(gen, x))
    return lambda x: f(jnp.asarray(x, float))


@pytest.fixture(scope="session")
def smoke_cache(tmp_path_factory):
    """A dataset cache holding the smoke train/test pair, generated once per test run: the
    pytest-xdist workers share it (the first generates it under a lock, the others load it)."""
    import fcntl

    from experiments.runs.config import conf
    from gpg.data.cache import ensure_datasets

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # common to the workers of this run
    cache = root / "smoke_cache"
    cache.mkdir(exist_ok=True)
    data = conf("smoke", "data")
    data["chunk"] = 32
    with open(root / "smoke_cache.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        ensure_datasets(data, conf("sui_endurance", "vehicle"), cache, progress=False)
    return cache


@pytest.fixture(scope="session")
def smoke_compare(smoke_cache, tmp_path_factory):
    """One full comparison on smoke data: (run directory, results)."""
    from experiments.compare import model_configs
    from experiments.runs import compare
    from tests.helpers import compose_plain

    values = compose_plain(
        "compare",
        [
            "data=smoke",
            "data.chunk=32",
            f"cache_dir={smoke_cache}",
            "n_queries=20",
            "model_overrides={inducing: {points: 20}}",  # PIC on 60 points
        ],
    )
    out = tmp_path_factory.mktemp("smoke_compare")
    return out, compare.run(values, out, model_configs(values))


@pytest.fixture(scope="session")
def synthetic_surrogate():
    """A default-model (gpgs_hybrid) surrogate on 50 synthetic points with fixed
    hyperparameters: built in about a second, for the tests of what uses a surrogate."""
    from gpg.surrogate import Surrogate
    from tests.helpers import synthetic_dataset

    cfg = {
        "hyper": {"fit": False, "lengthscale": 0.8},
        "partition": {"bins": 3, "points_per_bin": None},
        "near": {"budget": 0.5, "points": None},
        "variance_dtype": "float64",
    }
    return Surrogate.fit(synthetic_dataset(50, seed=3)[0], "gpgs_hybrid", cfg)
