"""Latin hypercube, finite-difference steps, raw samples, and deterministic generation."""

import numpy as np
import pytest

from gpg.data.bounds import Bounds
from gpg.data.sampling import FDSteps, generate, latin_hypercube, raw_samples


def test_latin_hypercube_stratified_and_in_bounds():
    b = Bounds()
    x = latin_hypercube(50, b, seed=4)
    lo, hi = b.arrays()
    assert x.shape == (50, 8) and np.all(x >= lo) and np.all(x <= hi)
    for j in range(8):  # one point per stratum in every dimension
        strata = np.floor((x[:, j] - lo[j]) / (hi[j] - lo[j]) * 50).astype(int)
        assert sorted(strata) == list(range(50))
    np.testing.assert_array_equal(x, latin_hypercube(50, b, seed=4))
    assert not np.array_equal(x, latin_hypercube(50, b, seed=5))
    np.testing.assert_allclose(hi[4:7], np.deg2rad([90, 60, 90]))


@pytest.mark.parametrize(
    "cfg, match",
    [
        ({"rpm": [7000.0, 0.0]}, r"bounds.rpm is inverted"),
        ({"pitch_deg": [10.0, 10.0]}, r"bounds.pitch_deg is inverted or empty"),
        ({"yaw": [0, 1]}, r"unknown bounds keys \['yaw'\]"),
        ({"airspeed": [-5.0, 5.0]}, r"must start at >= 0"),
        ({"roll_deg": [0.0]}, r"must be \[lower, upper\]"),
        ({"roll_deg": [0.0, float("inf")]}, r"must be finite"),
    ],
)
def test_bad_bounds(cfg, match):
    with pytest.raises(ValueError, match=match):
        Bounds.from_config(cfg)


def test_fd_steps_and_raw_layout():
    x = np.array([[0.0, 100.0, 3000.0, 7000.0, 0.1, 0.2, 0.3, 5.0]])
    raw, h = raw_samples(x, FDSteps())
    np.testing.assert_allclose(h[0], [10.0, 10.0, 300.0, 700.0] + [np.pi / 180] * 3)
    assert raw.shape == (8, 8)
    np.testing.assert_array_equal(raw[0], x[0])
    for k in range(7):
        d = raw[1 + k] - x[0]
        assert np.count_nonzero(d) == 1 and np.isclose(d[k], h[0, k], rtol=1e-12)
    with pytest.raises(ValueError, match="fd.rpm_rel must be > 0"):
        FDSteps(rpm_rel=0.0)


def test_generate_fd_is_paper_forward_difference(gen):
    ds = generate(gen, 4, seed=2, chunk=32)
    y8 = ds.y_raw.reshape(4, 8, 9)
    _, h = raw_samples(ds.x, FDSteps())
    np.testing.assert_allclose(
        ds.jac_aero[:, 0, 5], (y8[:, 6, 0] - y8[:, 0, 0]) / h[:, 5], rtol=1e-12
    )
    np.testing.assert_array_equal(ds.y_aero, y8[:, 0, :6])
    assert ds.missing == ()


def test_generate_is_bit_identical(gen, tmp_path):
    for name in ("a", "b"):
        generate(gen, 4, seed=2, chunk=32, meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}}).save(
            tmp_path / name
        )
    for ext in (".npz", ".json"):
        assert (tmp_path / f"a{ext}").read_bytes() == (tmp_path / f"b{ext}").read_bytes()


def test_generate_options(gen):
    with pytest.raises(ValueError, match="gradients must be"):
        generate(gen, 2, gradients="adjoint")
    with pytest.raises(ValueError, match="raw 8X samples come from the finite differences"):
        generate(gen, 2, gradients="none")
    ds = generate(gen, 3, gradients="none", keep_raw=False, noise=False, chunk=32)
    assert ds.missing == ("noise", "gradients", "raw samples")


@pytest.mark.slow
def test_generation_is_bit_identical_with_one_and_four_worker_processes(vehicle, tmp_path):
    import os

    import jax

    from gpg.quadrotor import acoustics, bemt
    from gpg.quadrotor.generator import Generator

    # A coarse generator compiles quickly in each of the four spawned workers; they share the
    # session's compilation cache through the environment (spawn inherits it).
    gen = Generator(
        vehicle,
        bemt.BEMTConfig(n_radial=6, n_azimuth=8, coarse_radial=4, coarse_azimuth=4),
        acoustics.AcousticsConfig(n_harmonics=2, thickness_stations=4),
    )
    env = {
        "JAX_COMPILATION_CACHE_DIR": str(jax.config.jax_compilation_cache_dir),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
    }
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        meta = {"simple_model": {"P_F": 1.0, "T_z": 1.0}}
        for name, workers in (("one", 1), ("four", 4)):
            ds = generate(gen, 20, seed=3, chunk=16, meta=meta, workers=workers)
            ds.save(tmp_path / name)  # 160 raw rows: ten chunks shared by the workers
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    for ext in (".npz", ".json"):
        assert (tmp_path / f"one{ext}").read_bytes() == (tmp_path / f"four{ext}").read_bytes()


def test_workers_must_be_a_positive_integer(gen):
    with pytest.raises(ValueError, match="workers must be a positive integer, got 0"):
        generate(gen, 2, chunk=32, workers=0)


def test_body_frame_sampling_covers_the_ball_from_every_direction():
    """Body frame: rotor speeds stratified in their box, air velocities inside the ball of
    radius 20 m/s with the speed stratified (one point per stratum) and directions on the
    whole sphere: every octant, air from behind (u < 0), climb and descent (w of both signs)."""
    x = latin_hypercube(400, Bounds(), seed=1, frame="body")
    assert x.shape == (400, 7)
    speed = np.linalg.norm(x[:, 4:], axis=1)
    assert speed.max() <= 20.0 * (1 + 1e-12)
    assert sorted(np.floor(speed / 20.0 * 400).astype(int)) == list(range(400))
    octants = {tuple(s) for s in (np.sign(x[:, 4:]) > 0).astype(int)}
    assert len(octants) == 8
    d = x[:, 4:] / speed[:, None]
    assert abs(np.mean(d[:, 2])) < 0.1 and abs(np.mean(d[:, 0])) < 0.1  # uniform on the sphere
    with pytest.raises(ValueError, match="frame must be 'airflow' or 'body'"):
        latin_hypercube(3, Bounds(), seed=0, frame="wind")


def test_body_frame_differences_step_the_air_velocity():
    x = np.array([[3000.0, 3000.0, 3000.0, 3000.0, -2.0, 0.5, 3.0]])
    raw, h = raw_samples(x, FDSteps(velocity=0.05))
    assert raw.shape == (8, 7)
    np.testing.assert_allclose(h[0], [300.0] * 4 + [0.05] * 3)
    for k in range(7):
        d = raw[1 + k] - x[0]
        assert np.count_nonzero(d) == 1 and np.isclose(d[k], h[0, k], rtol=1e-12)
