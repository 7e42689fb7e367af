"""The real-time surrogate (paper, Sections "Aerodynamic Surrogate" and "Real-time Simulation").

``predict(rpm, euler, v_air)`` for one vehicle state in the world frame:

1. airflow frame ``H`` (``R_WH e_x = v̂``, a proper rotation; below ``hover_speed`` it turns
   toward the body heading, where the direction no longer matters) and the attitude in it,
   ``x_H = (r1..r4, ψ_H, θ_H, φ_H, ‖v_air‖)``;
2. normalise, find the bin, evaluate the GP (mean, and the latent variance);
3. de-normalise: force/moment residuals in ``H``, noise levels as they are;
4. rotate the residual force and moment back to the world frame and add the simplified model
   ``M`` evaluated at the world attitude: ``F_W = R_WH μ_F + F_M,W`` (likewise the moment).

The body frame (a surrogate fitted on body-frame data, ``frame == "body"``): step 1 is
``x_B = (r1..r4, R_WBᵀ v_air)``, smooth everywhere, hover and vertical air included, with no
frame of its own to turn; the GP's residuals live in the body frame, ``F_W = R_WB μ_F + F_M,W``.
Its ``in_domain`` is the rotor speeds' box and the ball of air velocities of the data (the
largest ball about hover inside their box: ``|v_air| ≤ V``).

``in_domain`` is False when an rpm is negative or ``x_H`` leaves the training box (e.g. flying
sideways or backwards puts ``ψ_H`` beyond ±90°), or where the airflow frame turns faster than
:data:`MAX_FRAME_RATE` with the air velocity (next to its singular sets, where 1 mm/s of air
would move the prediction by a finite step): the prediction is still returned, but it is an
extrapolation and says so.

``half_turn`` (``fit(half_turn=True)``, for a vehicle that is its own image under a half turn
about its z axis with r1 ↔ r3 and r2 ↔ r4): a state whose airflow comes from behind
(``cos ψ_H < 0``) is read at its image (:func:`gpg.quadrotor.frames.half_turn`), the same
physical state seen with the body frame turned, whose airflow comes from the front where the
data are. ``M`` stays at the state as given; the world-frame loads are the image's.

NaN and inf: a call from Python (``predict``, ``predict_mean``, the ``realtime`` closures,
``predict_batch``) with a non-finite input raises ``ValueError`` naming it. Under the caller's
own ``jit``/``vmap``/``scan`` nothing can be raised: the outputs are then non-finite and
``in_domain`` is False, the flag to check.

Everything is one jittable function of arrays: it vmaps over batches, runs inside
``lax.scan``, and ``predict_batch`` processes large batches in chunks of bounded memory.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from gpg import _host, models, parallel
from gpg._checks import no_hash
from gpg._deprecated import deprecated
from gpg._dtype import float64
from gpg._precision import highest
from gpg.config import ModelConfig
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.preprocess import Normalizer, Training, simple_model_for
from gpg.gp.predictor import Predictor
from gpg.quadrotor.dynamics import AeroModel, Rotation, RotorSpeeds, Vector3, Wrench
from gpg.quadrotor.frames import (
    R_WB,
    airflow_frame_rate,
    euler_from_R,
    half_turn,
    matmul,
    matvec,
    to_airflow_frame,
)
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise
from gpg.quadrotor.vehicle import Vehicle, load_vehicle

__all__ = [
    "CHUNKS",
    "HOVER_SPEED",
    "MAX_FRAME_RATE",
    "Prediction",
    "Replicated",
    "Surrogate",
    "SurrogateAero",
    "dataset_vehicle",
    "default_chunk",
    "domain_box",
    "gp_inputs",
    "predict_state",
]


class Prediction(eqx.Module):
    """World-frame prediction for one state (or a batch, with a leading axis).

    ``force`` (3,) N and ``torque`` (3,) N·m about the centre of mass, aerodynamic only (add
    gravity yourself); ``levels`` (K,) tonal noise levels in dB at the K microphones (K = 0
    without level data; called ``noise`` before gpg 0.2, a name still read with a warning);
    ``variance`` (6+K,) predictive variance of each of those components in the same frame and
    units: the GP's latent variance plus its fitted value noise ``ν²``, times each output's
    signal scale (None from ``predict_mean``); ``in_domain`` False for extrapolation or bad input.
    """

    force: Float[Array, "*batch 3"]
    torque: Float[Array, "*batch 3"]
    levels: Float[Array, "*batch K"]
    variance: Float[Array, "*batch C"] | None
    in_domain: Bool[Array, "*batch"]

    @property
    def noise(self) -> Float[Array, "*batch K"]:
        """Deprecated name of :attr:`levels` (the dB levels; ``noise`` is ν², the value noise)."""
        deprecated("Prediction.noise", "Prediction.levels")
        return self.levels


# Below this airspeed (m/s) the airflow frame follows the body heading. Small against the
# hover induced velocity (about 5 m/s) and the 2 m/s airspeed bins, large against the drift a
# position controller leaves in hover.
HOVER_SPEED = 0.5
# rad per m/s: the fastest the airflow-frame coordinates of an in-domain query may turn with
# the air velocity (frames.airflow_frame_rate), so that 1 mm/s of air turns them by at most
# 0.6°. Away from the frame's singular sets the rate is about 1/airspeed, 1/HOVER_SPEED in hover.
MAX_FRAME_RATE = 10.0


class Surrogate(eqx.Module):
    """A fitted model plus everything to go from a world-frame state to world-frame outputs."""

    __hash__ = no_hash  # jax.jit(model.predict): say what to call instead

    model: Predictor
    normalizer: Normalizer
    simple: SimpleModel | None
    box_lo: Float[Array, " 8"]  # training box of x_H (rpm, rad, m/s); (7,) in the body frame
    box_hi: Float[Array, " 8"]
    output_names: tuple[str, ...] = eqx.field(static=True)
    model_name: str = eqx.field(static=True)
    config_json: str = eqx.field(static=True)  # resolved model config, for records
    # m/s: below it the airflow frame turns toward the body heading (frames.airflow_direction)
    hover_speed: float = eqx.field(static=True, default=HOVER_SPEED)
    noise_model: SimpleNoise | None = None  # M_noise, added back to the levels (None: not used)
    # "airflow": the paper's inputs x_H; "body": x_B = (rpm, R_WBᵀ v_air) (gpg.names.FRAMES)
    frame: str = eqx.field(static=True, default="airflow")
    # Airflow from behind read at the state's image under the half turn (frames.half_turn):
    # set by ``fit(half_turn=True)`` after the vehicle's symmetry is checked.
    half_turn: bool = eqx.field(static=True, default=False)

    @classmethod
    @float64
    def fit(
        cls,
        dataset: Dataset,
        model: str = "gpgs_hybrid",
        config: Mapping[str, Any] | None = None,
        *,
        vehicle: Vehicle | str | Path | None = None,
        bounds: Mapping[str, Any] | None = None,
        residual: bool = True,
        noise_model: bool = False,
        hover_speed: float = HOVER_SPEED,
        half_turn: bool = False,
        devices: parallel.Devices = None,
    ) -> Surrogate:
        """Preprocess ``dataset`` and build ``model`` around it: data to a world-frame surrogate.

        The default model, ``gpgs_hybrid``, has exactly GP-G's mean (continuous, from all
        points) and a near-set variance that bounds GP-G's from above, at a fixed per-query
        cost (README "Results"). A dataset that names no vehicle, given no ``vehicle``, is an
        error rather than a silent default: another vehicle's geometry would corrupt ``M``.

        Args:
            dataset: the training data, airflow or body frame (:attr:`Dataset.frame`).
            model: a name from :data:`gpg.models.NAMES`.
            config: overrides of the model's defaults (:func:`gpg.models.resolve_config`),
                e.g. ``{"hyper": {"subset": 60}}``.
            vehicle: a :class:`Vehicle`, a name in ``conf/vehicle`` or a YAML path; it
                supplies the rotor layout and, if its file has them, the coefficients of the
                simplified model ``M``. None takes the vehicle the dataset names
                (:func:`dataset_vehicle`).
            bounds: the input box outside which ``in_domain`` is False, in the ``data.bounds``
                form (``rpm``, ``yaw_deg``, …); None takes :func:`domain_box` (the dataset's
                recorded sampling bounds, else its extent).
            residual: fit the residuals against ``M`` (the paper's method); False fits the raw
                outputs without ``M`` and needs no vehicle.
            noise_model: also subtract ``M_noise`` (tonal levels from ``M``'s loads) from the
                levels and add it back at prediction; needs ``residual``.
            hover_speed: the airspeed in m/s below which the airflow frame turns toward the
                body heading (0: pure wind axes).
            half_turn: read a state whose airflow comes from behind (``cos ψ_H < 0``) at its
                image under a half turn about the body z axis with the rotors relabelled
                (:func:`gpg.quadrotor.frames.half_turn`): the same physical state, whose
                airflow comes from the front, where the data are. The vehicle must be its own
                image (:meth:`Vehicle.half_turn_asymmetries`, microphones included where the
                data have levels); airflow frame only.
            devices: a count or a list of JAX devices over which the per-bin precompute of
                the local models is spread (:mod:`gpg.parallel`); None for one process.

        Returns:
            The fitted surrogate, in float64.

        Raises:
            ValueError: if ``noise_model`` is set without ``residual``; if ``half_turn`` is set
                for body-frame data or a vehicle that is not its own image, naming what
                differs; and as
                :func:`gpg.models.resolve_config`, :func:`dataset_vehicle` and
                :func:`gpg.models.build` raise it (bad options, no vehicle, data the model
                cannot train on).
        """
        cfg = models.resolve_config(model, config)
        box = None if bounds is None else Bounds.from_config(bounds).arrays(dataset.frame)
        if noise_model and not residual:
            raise ValueError("noise_model=True needs residual=True (M_noise uses M's loads)")
        simple = noise = None  # M and M_noise
        veh = dataset_vehicle(dataset, vehicle) if residual or half_turn else None
        if half_turn:
            _check_half_turn(dataset, veh)
        if residual:
            simple = simple_model_for(dataset, veh)
            if noise_model and dataset.has_noise:
                noise = SimpleNoise.from_vehicle(veh, simple)
        training, built = models.train(
            model, dataset, simple, cfg, noise_model=noise, devices=devices
        )
        return cls.assemble(built.model, training, dataset, model, cfg, hover_speed=hover_speed,
                            box=box, half_turn=half_turn)  # fmt: skip

    @classmethod
    def assemble(
        cls,
        model: Predictor,
        training: Training,
        dataset: Dataset,
        model_name: str,
        config: ModelConfig | Mapping[str, Any],
        *,
        hover_speed: float = HOVER_SPEED,
        box: tuple[np.ndarray, np.ndarray] | None = None,
        half_turn: bool = False,
    ) -> Surrogate:
        """A surrogate around an already built ``model``.

        Args:
            model: the built predictor (e.g. :attr:`gpg.models.Built.model`).
            training: what ``model`` was trained on, the output of :func:`gpg.data.prepare` for
                ``dataset``: its normaliser, ``M`` and ``M_noise`` are kept.
            dataset: the training data, for the frame and the domain box.
            model_name: the model's name, kept for records and checkpoints.
            config: the model's resolved config, kept as JSON.
            hover_speed: the airspeed in m/s below which the airflow frame turns toward the
                body heading.
            box: (lo, hi) input bounds of ``in_domain``; None takes :func:`domain_box`.
            half_turn: airflow from behind read at the state's half-turn image (:meth:`fit`,
                which checks the vehicle; here the caller vouches for it).

        Returns:
            The surrogate.

        Raises:
            ValueError: if ``hover_speed`` is negative or not finite, or ``half_turn`` is set
                for body-frame data.
        """
        if half_turn and dataset.frame != "airflow":
            raise ValueError(
                f"half_turn needs airflow-frame data, got frame {dataset.frame!r} (the body "
                "frame's ball of air velocities is its own image)"
            )
        hover_speed = float(hover_speed)
        if not np.isfinite(hover_speed) or hover_speed < 0.0:
            raise ValueError(f"hover_speed must be a finite speed >= 0 m/s, got {hover_speed}")
        box_lo, box_hi = domain_box(dataset) if box is None else box
        return cls(
            model=model,
            normalizer=training.normalizer,
            simple=training.simple,
            noise_model=training.noise_model,
            box_lo=jnp.asarray(box_lo),
            box_hi=jnp.asarray(box_hi),
            output_names=training.output_names,
            model_name=model_name,
            config_json=json.dumps(
                config.to_dict() if isinstance(config, ModelConfig) else config, sort_keys=True
            ),
            hover_speed=hover_speed,
            frame=dataset.frame,
            half_turn=bool(half_turn),
        )

    def condition(self, dataset: Dataset) -> Surrogate:
        """This surrogate conditioned on the cases of ``dataset``, without a refit.

        The hyperparameters, normaliser, ``M`` and bins are kept: the result is the same model
        as a rebuild with them (to rounding). ``gpg``/``gp`` update by a bordered Cholesky,
        ``gpgs_hybrid`` by re-forming ``α`` and the bins whose near set changed
        (:mod:`gpg.design` says when to refit instead). This surrogate is never changed.

        Args:
            dataset: the new cases, with the training data's outputs; they may carry any
                subset of the gradients (NaN for a perturbation not run).

        Returns:
            A new surrogate that has seen the training cases and ``dataset``'s.

        Raises:
            ValueError: from :func:`gpg.design.condition`, for bad cases (other outputs,
                outside the box, duplicates of training cases, NaN).
        """
        from gpg import design

        return design.condition(self, dataset)

    @property
    def config(self) -> dict[str, Any]:
        return json.loads(self.config_json)

    @property
    def n_levels(self) -> int:
        """Number of level outputs (microphones)."""
        return len(self.output_names) - 6

    @property
    def n_noise(self) -> int:
        """Deprecated name of :attr:`n_levels`."""
        deprecated("Surrogate.n_noise", "Surrogate.n_levels")
        return self.n_levels

    @property
    def noise(self) -> SimpleNoise | None:
        """Deprecated name of :attr:`noise_model` (``M_noise``)."""
        deprecated("Surrogate.noise", "Surrogate.noise_model")
        return self.noise_model

    # -- prediction -------------------------------------------------------------------------

    def predict(
        self,
        rpm: Float[ArrayLike, " 4"],
        euler: Float[ArrayLike, " 3"],
        v_air: Float[ArrayLike, " 3"],
    ) -> Prediction:
        """Force, torque, levels, their variances and ``in_domain`` for one state (jitted).

        Args:
            rpm: (4,) rotor speeds r1..r4.
            euler: (3,) yaw, pitch, roll of the body in the world frame, rad.
            v_air: (3,) vehicle velocity minus wind, world frame, m/s.

        Returns:
            The world-frame prediction with its variance.

        Raises:
            ValueError: called from Python, if an input has the wrong shape, is complex or
                boolean, or holds NaN or inf (under a transform: ``in_domain`` False instead).
        """
        return _predict(self, *_as_state(rpm, euler, v_air), True)

    def predict_mean(
        self,
        rpm: Float[ArrayLike, " 4"],
        euler: Float[ArrayLike, " 3"],
        v_air: Float[ArrayLike, " 3"],
    ) -> Prediction:
        """The fast path: as :meth:`predict` without the variance.

        Args:
            rpm: (4,) rotor speeds r1..r4.
            euler: (3,) body attitude (yaw, pitch, roll) in the world frame, rad.
            v_air: (3,) world-frame air velocity (vehicle minus wind), m/s.

        Returns:
            The prediction, its ``variance`` None.

        Raises:
            ValueError: as :meth:`predict` raises it, for a bad input.
        """
        return _predict(self, *_as_state(rpm, euler, v_air), False)

    def predict_body(
        self,
        rpm: Float[ArrayLike, " 4"],
        R_WB: Float[ArrayLike, "3 3"],
        v_air_body: Float[ArrayLike, " 3"],
        *,
        with_var: bool = True,
    ) -> Prediction:
        """The body-frame entry point, for simulators that integrate in the body frame.

        Other simulators' conventions (z up, FLU, xyzw quaternions, rad/s) are converted by
        :mod:`gpg.adapters.conventions`. Jittable and differentiable like :meth:`predict`.

        Args:
            rpm: (4,) rotor speeds r1..r4.
            R_WB: (3, 3) attitude, body FRD to world NED.
            v_air_body: (3,) airspeed in the body frame, ``R_WBᵀ (v_vehicle − v_wind)``, m/s.
            with_var: also compute the variances.

        Returns:
            The aerodynamic force (N) and torque (N·m) in the body frame (FRD), their
                predictive variances in that frame (None without ``with_var``), the levels and
                ``in_domain``.

        Raises:
            ValueError: called from Python, if ``R_WB`` is not a rotation matrix or an input
                has the wrong shape or holds NaN or inf.
        """
        R = _as_rotation(R_WB)
        rpm, _, v_b = _as_state(rpm, np.zeros(3), v_air_body)
        return _predict_body(self, rpm, R, v_b, bool(with_var))

    @property
    def ball_radius(self) -> Float[Array, ""]:
        """The body frame's ``V``: ``in_domain`` holds air velocities ``|R_WBᵀ v_air| ≤ V``,
        the largest ball about hover inside the box of ``u, v, w`` (m/s). Body frame only."""
        return jnp.minimum(jnp.min(self.box_hi[4:]), jnp.min(-self.box_lo[4:]))

    def predict_batch(
        self,
        rpm: Float[ArrayLike, "N 4"],
        euler: Float[ArrayLike, "N 3"],
        v_air: Float[ArrayLike, "N 3"],
        *,
        mean_only: bool = False,
        chunk: int | None = None,
    ) -> Prediction:
        """Many states, vmapped in chunks: bounded memory for any N.

        JAX arrays stay on their device; the variance of a partitioned model is formed bin by
        bin within each chunk (:func:`gpg.gp.binned.by_bin`).

        Args:
            rpm: (N, 4) rotor speeds.
            euler: (N, 3) attitudes (yaw, pitch, roll), rad.
            v_air: (N, 3) world-frame air velocities, m/s.
            mean_only: skip the variance (``variance`` None).
            chunk: states per vmapped block; None takes :func:`default_chunk` for the backend.

        Returns:
            The predictions, each field with a leading axis of N.

        Raises:
            ValueError: if the shapes do not match (N, 4), (N, 3), (N, 3), ``chunk`` is not a
                positive integer, or a state holds NaN or inf (naming the input and its rows).
        """
        rpm, euler, v_air = _check_batch(rpm, euler, v_air, chunk)
        chunk = default_chunk(not mean_only) if chunk is None else int(chunk)
        return _predict_batch(self, rpm, euler, v_air, not mean_only, chunk)

    def variance_parts(
        self,
        rpm: Float[ArrayLike, "N 4"],
        euler: Float[ArrayLike, "N 3"],
        v_air: Float[ArrayLike, "N 3"],
    ) -> dict[str, Float[Array, "N M"]]:
        """Where the band's width comes from: :meth:`predict_batch`'s ``variance`` split into
        the model's terms (:meth:`gpg.gp.predictor.Predictor.variance_parts`; for a flight
        correction the prior's, the discrepancies', their noise and the physical
        coefficients'), each in the world frame as ``variance`` is.

        Args:
            rpm: (N, 4) rotor speeds.
            euler: (N, 3) attitudes (yaw, pitch, roll), rad.
            v_air: (N, 3) world-frame air velocities, m/s.

        Returns:
            Each term's (N, M) variance; they sum to ``predict_batch(...).variance``.

        Raises:
            ValueError: a bad input, as :meth:`predict_batch` names it, or a model whose band
                is not a sum of terms (an adapted flight correction).
        """
        rpm, euler, v_air = _check_batch(rpm, euler, v_air, None)
        chunk = default_chunk(True)
        parts = [_variance_parts(self, *(a[i : i + chunk] for a in (rpm, euler, v_air)))
                 for i in range(0, max(rpm.shape[0], 1), chunk)]  # fmt: skip
        return {k: jnp.concatenate([p[k] for p in parts]) for k in parts[0]}

    def replicate(self, devices: parallel.Devices = None) -> Replicated:
        """This surrogate copied onto several JAX devices, for batched prediction spread over them.

        Args:
            devices: a count (the first n of ``jax.devices()``) or a list of devices
                (:func:`gpg.parallel.devices`); None for the first device.

        Returns:
            The copies, whose :meth:`Replicated.predict_batch` spreads blocks over the devices.

        Raises:
            ValueError: from :func:`gpg.parallel.devices`, for a bad ``devices``.
        """
        return Replicated(self, parallel.devices(devices))

    def realtime(self, *, with_var: bool = True) -> Callable[..., Prediction]:
        """A compiled ``f(rpm, euler, v_air) -> Prediction`` for loops that call it per step.

        Same result as :meth:`predict`, but the surrogate's arrays are flattened once here
        instead of at every call: flattening an equinox module costs more than the whole mean
        prediction (see ``experiments/bench.py``). Inside your own ``jit``/``vmap``/``scan``
        use :meth:`predict`, which costs nothing there. Without ``with_var`` only the arrays
        the mean reads are passed: each array passed to a compiled function adds to the cost
        of every call, and a partitioned model's variance factors are hundreds of arrays (see
        docs/measurements.md).

        Args:
            with_var: compute the variance, as :meth:`predict`; False is
                :meth:`predict_mean`.

        Returns:
            The function of one state, which checks its inputs as :meth:`predict` does.
        """
        sur = self if with_var else eqx.tree_at(lambda s: s.model, self, self.model.mean_view())
        leaves, treedef = jax.tree_util.tree_flatten(sur)
        fn = _realtime_fn(treedef, with_var)
        leaves = tuple(leaves)

        def predict(rpm, euler, v_air) -> Prediction:
            return fn(leaves, *_as_state(rpm, euler, v_air))

        return predict

    def nbytes(self) -> int:
        """The memory of the fitted model's arrays.

        Returns:
            Bytes, as :meth:`gpg.gp.predictor.Predictor.nbytes` counts them.
        """
        return self.model.nbytes()

    def astype(self, dtype: DTypeLike) -> Surrogate:
        """A copy with every float array in ``dtype``; queries are then computed in ``dtype``.

        A fitted surrogate holds float64 arrays. For float32 programs (``jax_enable_x64`` off:
        JAX would otherwise convert the float64 arrays at every call) or float32 rollouts, use
        ``sur.astype(jnp.float32)`` once; its accuracy against float64 is measured by
        ``experiments/bench.py`` (README Measurements). Fitting always runs in float64.

        Args:
            dtype: a floating dtype, e.g. ``jnp.float32``.

        Returns:
            The converted copy; integer and other arrays are kept as they are.

        Raises:
            ValueError: if ``dtype`` is not a floating type.
        """
        dtype = jnp.dtype(dtype)
        if not jnp.issubdtype(dtype, jnp.floating):
            raise ValueError(f"dtype must be a floating type, got {dtype}")

        leaves, treedef = jax.tree.flatten(self)
        # the float arrays not already in dtype, converted in one program (op by op, one
        # compiled for every leaf's shape); the others kept, as jnp.asarray keeps them
        moved = [i for i, x in enumerate(leaves)
                 if isinstance(x, jax.Array | np.ndarray) and jnp.issubdtype(x.dtype, jnp.floating)
                 and not (isinstance(x, jax.Array) and x.dtype == dtype)]  # fmt: skip
        if moved:
            for i, x in zip(moved, _cast(tuple(leaves[i] for i in moved), dtype), strict=True):
                leaves[i] = x
        return jax.tree.unflatten(treedef, leaves)


class Replicated:
    """A :class:`Surrogate` with one copy per device (:meth:`Surrogate.replicate`).

    The copies are made once, here; :meth:`predict_batch` then sends each block of ``chunk``
    queries to the next device (round robin) and JAX runs the blocks side by side. Every block
    runs the same compiled program, so the result is bit-identical for any number of devices.
    """

    def __init__(self, sur: Surrogate, devs: list[jax.Device]):
        self.surrogate = sur
        self.devices = devs
        mean = eqx.tree_at(lambda s: s.model, sur, sur.model.mean_view())
        self._replicas = {
            True: parallel.replicate(sur, devs),
            False: parallel.replicate(mean, devs),
        }

    def predict_batch(
        self,
        rpm: Float[ArrayLike, "N 4"],
        euler: Float[ArrayLike, "N 3"],
        v_air: Float[ArrayLike, "N 3"],
        *,
        mean_only: bool = False,
        chunk: int = 1024,
    ) -> Prediction:
        """As :meth:`Surrogate.predict_batch`, its blocks of ``chunk`` states over the devices.

        The last block is padded to ``chunk`` states, so that every block runs one compiled
        program.

        Args:
            rpm: (N, 4) rotor speeds.
            euler: (N, 3) yaw, pitch and roll, rad.
            v_air: (N, 3) air velocities in the world frame, m/s.
            mean_only: skip the variance.
            chunk: states per block, one block per device at a time.

        Returns:
            The predictions as NumPy arrays, each with a leading axis of N.

        Raises:
            ValueError: as :meth:`Surrogate.predict_batch` raises it, for bad inputs.
        """
        rpm, euler, v_air = (np.asarray(a) for a in _check_batch(rpm, euler, v_air, chunk))
        n, chunk = rpm.shape[0], int(chunk)
        units = []
        for sl in parallel.chunks(n, chunk):
            block = [a[sl] for a in (rpm, euler, v_air)]
            pad = chunk - block[0].shape[0]  # the last block padded: one program for all
            units.append(tuple(np.concatenate([b, np.repeat(b[-1:], pad, 0)]) for b in block))
        with_var = not mean_only
        fn = partial(_predict_batch, with_var=with_var, chunk=chunk)
        out = parallel.map_units(fn, None, units, self.devices, replicas=self._replicas[with_var])
        if not out:
            return jax.tree.map(
                np.asarray, _predict_batch(self.surrogate, rpm, euler, v_air, with_var, chunk)
            )
        return jax.tree.map(lambda *p: np.concatenate(p)[:n], *out)


def _check_batch(rpm, euler, v_air, chunk):
    """``(rpm, euler, v_air)`` as float arrays of a batch, or ``ValueError`` naming the input."""
    for name, a in (("rpm", rpm), ("euler", euler), ("v_air", v_air)):
        _require_real(name, a)
    rpm, euler, v_air = (
        _batch_array(n, a) for n, a in (("rpm", rpm), ("euler", euler), ("v_air", v_air))
    )
    for name, a, w in (("rpm", rpm, 4), ("euler", euler, 3), ("v_air", v_air, 3)):
        if a.ndim != 2 or a.shape[1] != w:
            raise ValueError(f"{name} must have shape (N, {w}), got {a.shape}")
    if not rpm.shape[0] == euler.shape[0] == v_air.shape[0]:
        raise ValueError(f"batch sizes differ: {rpm.shape[0]}, {euler.shape[0]}, {v_air.shape[0]}")
    for name, a in (("rpm", rpm), ("euler", euler), ("v_air", v_air)):
        _require_finite(name, a)
    if chunk is not None and (isinstance(chunk, bool) or int(chunk) != chunk or chunk < 1):
        raise ValueError(f"chunk must be a positive integer or None, got {chunk!r}")
    return rpm, euler, v_air


def _batch_array(name: str, a):
    """A batch input as a JAX array: a JAX float array stays where it is (a GPU's states are
    not copied to the host to be checked), anything else is converted on the host."""
    if isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.floating):
        return a
    return _host.asarray(_as_float(name, a))


# Queries per vmapped block of predict_batch, per JAX backend, for the mean alone and with
# the variance: a block's kernel rows and variance products are its working memory (per
# query, see docs/measurements.md). On the CPU the mean is fastest in blocks that stay in
# cache, the variance in blocks long enough to fill each bin's tiles
# (gpg.gp.binned.by_bin); a GPU wants long blocks for both (one launch per block).
# experiments.bench 'suites=[gpu]' times several (docs/measurements.md).
CHUNKS = {"cpu": (1024, 4096), "gpu": (65536, 65536)}


def default_chunk(with_var: bool = True) -> int:
    """The states per vmapped block of :meth:`Surrogate.predict_batch` on this backend.

    Args:
        with_var: the block for a prediction with the variance; False for the mean alone.

    Returns:
        The entry of :data:`CHUNKS` for JAX's default backend (the CPU's on a backend it does
            not list).
    """
    return CHUNKS.get(jax.default_backend(), CHUNKS["cpu"])[int(with_var)]


def domain_box(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The input box the training data were meant to cover: ``in_domain``'s default bounds.

    The sampling bounds recorded by the generator or given to :func:`gpg.data.from_csv` (so
    hover at exactly 0 m/s is inside), else the data's own extent. In the body frame the
    extent of ``u, v, w`` is the ball of the data's largest airspeed (``±V`` on each, as the
    bounds give it): the box of the cases' own velocities need not hold hover, and the ball
    about hover inside it would be empty.

    Args:
        dataset: the training data.

    Returns:
        The lower and upper bounds of the inputs, each of the frame's input size.
    """
    bounds = dataset.meta.get("bounds")
    if bounds:
        return Bounds.from_config(bounds).arrays(dataset.frame)
    lo, hi = dataset.x.min(0), dataset.x.max(0)
    if dataset.frame == "body":
        speed = float(np.max(dataset.airspeed))
        lo[4:], hi[4:] = -speed, speed
    return lo, hi


def dataset_vehicle(dataset: Dataset, vehicle: Vehicle | str | Path | None = None) -> Vehicle:
    """The vehicle of ``dataset``; there is no default, since another vehicle's geometry
    would silently corrupt the simplified model.

    Args:
        dataset: the data, which may record its vehicle (:func:`gpg.data.from_csv` or the
            generator).
        vehicle: a :class:`Vehicle`, a name in ``conf/vehicle`` or a YAML path, taken when
            given; None takes the one the dataset names.

    Returns:
        The vehicle.

    Raises:
        ValueError: if neither ``vehicle`` nor the dataset names one, or the dataset names a
            vehicle not in ``conf/vehicle``.
    """
    if isinstance(vehicle, Vehicle):
        return vehicle
    if vehicle is not None:
        return load_vehicle(vehicle)
    recorded = dataset.meta.get("vehicle")
    if isinstance(recorded, Mapping):
        return Vehicle.from_config(recorded)
    name = dataset.meta.get("generator", {}).get("vehicle")
    if name:
        try:
            return load_vehicle(name)
        except ValueError as exc:
            raise ValueError(
                f"the dataset names vehicle {name!r}, which is not in conf/vehicle: pass "
                f"vehicle= (the Vehicle, or its YAML file) ({exc})"
            ) from exc
    raise ValueError(
        "the dataset names no vehicle: pass vehicle= (a gpg.quadrotor.Vehicle, a name in "
        "conf/vehicle or a vehicle YAML file), or import the data with "
        "gpg.data.from_csv(..., vehicle=...) so that the dataset records it"
    )


def _as_state(rpm, euler, v_air):
    """Check one state's shapes and (outside a transform) finiteness. Concrete inputs stay
    NumPy arrays: converting each to a JAX array first cost more than the mean prediction."""
    out = []
    for name, a, n in (("rpm", rpm, 4), ("euler", euler, 3), ("v_air", v_air, 3)):
        _require_real(name, a)
        a = jnp.asarray(a, dtype=float) if isinstance(a, jax.core.Tracer) else _as_float(name, a)
        if a.shape != (n,):
            raise ValueError(
                f"{name} must have shape ({n},) for one state, got {a.shape}; "
                "use jax.vmap or Surrogate.predict_batch for batches"
            )
        _require_finite(name, a)
        out.append(a)
    return tuple(out)


def _as_rotation(R):
    """A 3x3 attitude matrix, checked like :func:`_as_state` checks a state."""
    _require_real("R_WB", R)
    R = jnp.asarray(R, dtype=float) if isinstance(R, jax.core.Tracer) else _as_float("R_WB", R)
    if R.shape != (3, 3):
        raise ValueError(f"R_WB must be a 3x3 rotation matrix, got shape {R.shape}")
    _require_finite("R_WB", R)
    if not isinstance(R, jax.core.Tracer):
        err = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if err > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError(
                f"R_WB must be a rotation matrix (RᵀR = I, det +1); it is off by {err:.1e}"
            )
    return R


def _require_real(name: str, a) -> None:
    """Complex and boolean inputs are refused (checked on the dtype, also under a transform:
    an imaginary part would be dropped, a mask taken for numbers)."""
    dt = a.dtype if hasattr(a, "dtype") else np.asarray(a).dtype
    if np.issubdtype(dt, np.complexfloating) or dt == np.bool_:
        raise ValueError(f"{name} must be real numbers, got dtype {dt}")


def _as_float(name: str, a):
    """A concrete input as a float array, or ``ValueError`` naming it (text, huge integers)."""
    try:
        return np.asarray(a, float)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name} must be real numbers: {exc}") from None


@partial(jax.jit, static_argnums=(1,))
def _cast(arrays: tuple, dtype) -> tuple:
    """:meth:`Surrogate.astype`'s conversions, one program for a model's leaves."""
    return tuple(jnp.asarray(a, dtype=dtype) for a in arrays)


# One program per shape (op by op, the check compiled two)
_all_finite = jax.jit(lambda a: jnp.all(jnp.isfinite(a)))


def _require_finite(name: str, a) -> None:
    """The NaN/inf policy: a call from Python with a non-finite input raises ``ValueError``
    naming it; under the caller's own ``jit``/``vmap``/``scan`` (a tracer, nothing to inspect)
    the prediction comes back with ``in_domain`` False instead."""
    if isinstance(a, jax.core.Tracer):
        return
    if isinstance(a, jax.Array):
        with jax.ensure_compile_time_eval():  # a concrete array, also while a caller traces
            if bool(_all_finite(a)):
                return  # checked where it lives; only a failing input comes to the host
    v = np.asarray(a)
    if np.isfinite(v).all():
        return
    bad = ~np.isfinite(v)
    if bad.any():
        if v.ndim == 1:
            raise ValueError(f"{name} holds NaN or inf: {v.tolist()}")
        rows = np.flatnonzero(bad.reshape(v.shape[0], -1).any(1))
        more = f" (and {rows.size - 10} more)" if rows.size > 10 else ""
        raise ValueError(
            f"{name} holds NaN or inf in row(s) {rows[:10].tolist()}{more}, e.g. "
            f"{v[rows[0]].tolist()}"
        )


@highest
def predict_state(
    sur: Surrogate, rpm: Array, euler: Array, v_air: Array, with_var: bool, *, body: bool = False
) -> Prediction:
    """The un-jitted pipeline for one state (see the module docstring); jit, vmap or scan it.

    The state is computed in the surrogate's float dtype (:meth:`Surrogate.astype`). Nothing
    is raised here: a non-finite input or output gives ``in_domain`` False.

    Args:
        sur: the surrogate.
        rpm: (4,) rotor speeds.
        euler: (3,) world-frame attitude (yaw, pitch, roll), rad.
        v_air: (3,) world-frame air velocity, m/s.
        with_var: (static) also compute the variance.
        body: (static) force, torque and their variances in the body frame (FRD) instead of
            the world frame.

    Returns:
        The prediction (``variance`` None without ``with_var``).
    """
    sur, rpm, euler, v_air = _in_own_dtype(sur, rpm, euler, v_air)
    if (wind := getattr(sur.model, "wind_state", lambda: None)()) is not None:
        return _predict_in_wind(sur, wind, rpm, euler, v_air, with_var, body)
    x_h, R_WH, in_domain = _inputs(sur, rpm, euler, v_air)
    xn = sur.normalizer.x(x_h)
    if with_var:
        mean_n, var_n = sur.model.mean_var_one(xn)
    else:
        mean_n, var_n = sur.model.mean_one(xn), None
    y = sur.normalizer.y_inv(mean_n)
    # The GP's force and moment residuals live in H; R_out takes them to the output frame.
    R_out = matmul(R_WB(euler).T, R_WH) if body else R_WH
    force, torque = matvec(R_out, y[:3]), matvec(R_out, y[3:6])
    levels = y[6:] if sur.noise_model is None else y[6:] + sur.noise_model(x_h)
    if sur.simple is not None:
        if body:
            f_m, t_m = sur.simple.wrench_body(rpm)
        else:  # M at the world attitude, world frame
            y_m = sur.simple(jnp.concatenate([rpm, euler]))
            f_m, t_m = y_m[:3], y_m[3:6]
        force, torque = force + f_m, torque + t_m
    variance = None
    if with_var:
        # An observation's predictive variance per output, H frame: c_m (latent + ν²) std_m².
        v = sur.model.predictive_variance(var_n) * sur.normalizer.y_std**2
        variance = _rotated_variance(R_out, v)
    # A prediction that is not finite is never "in domain" (the flag to check under jit).
    outs = [force, torque, levels] + ([] if variance is None else [variance])
    in_domain = in_domain & jnp.all(jnp.stack([jnp.all(jnp.isfinite(o)) for o in outs]))
    return Prediction(
        force=force, torque=torque, levels=levels, variance=variance, in_domain=in_domain
    )


def _in_own_dtype(sur: Surrogate, *arrays):
    """The surrogate and the state's arrays in its float dtype as the program has it."""
    dt = jax.dtypes.canonicalize_dtype(sur.box_lo.dtype)  # float32 where x64 is off
    if sur.box_lo.dtype != dt:  # float64 arrays in a float32 program: convert once, explicitly
        sur = sur.astype(dt)
    return (sur, *(jnp.asarray(a).astype(dt) for a in arrays))


def gp_inputs(
    sur: Surrogate, rpm: Float[Array, "4"], euler: Float[Array, "3"], v_air: Float[Array, "3"]
) -> tuple[Float[Array, " D"], Float[Array, "3 3"]]:
    """The GP's input at a world-frame state, as :func:`predict_state` reads it: the paper's
    ``x_H = (r1..r4, ψ_H, θ_H, φ_H, ‖v_air‖)`` (the half-turn image's where the surrogate
    reads airflow from behind there), or ``x_B``; un-jitted, to vmap or jit. No domain test
    (the prediction's ``in_domain`` has it).

    Args:
        sur: the surrogate.
        rpm: (4,) rotor speeds.
        euler: (3,) world-frame attitude (yaw, pitch, roll), rad.
        v_air: (3,) world-frame air velocity, m/s.

    Returns:
        ``x`` in physical units (before the normaliser) and ``R_WH`` (world from the frame the
        GP's loads live in).
    """
    return _frame(sur, rpm, euler, v_air)[:2]


def _frame(sur: Surrogate, rpm, euler, v_air):
    """``x_h``, ``R_WH``, and the rotor speeds and attitude the GP reads the state at (the
    half-turn image's, where it applies)."""
    if sur.frame == "body":
        R_WH = R_WB(euler)  # the GP's frame is the body's
        return jnp.concatenate([rpm, matvec(R_WH.T, v_air)]), R_WH, rpm, euler
    euler_h, speed, R_WH = to_airflow_frame(euler, v_air, sur.hover_speed)
    if sur.half_turn:  # from behind: the same state, its body frame turned (fit's doc)
        rpm_t, euler_t = half_turn(rpm, euler)
        euler_ht, _, R_WHt = to_airflow_frame(euler_t, v_air, sur.hover_speed)
        back = jnp.cos(euler_h[0]) < 0.0
        rpm, euler = jnp.where(back, rpm_t, rpm), jnp.where(back, euler_t, euler)
        euler_h, R_WH = jnp.where(back, euler_ht, euler_h), jnp.where(back, R_WHt, R_WH)
    return jnp.concatenate([rpm, euler_h, speed[None]]), R_WH, rpm, euler


def _inputs(sur: Surrogate, rpm, euler, v_air):
    """The GP's input ``x_h`` at a state, ``R_WH`` (world from the GP's frame) and whether
    the state is in the data's domain, as far as the inputs tell."""
    finite = (
        jnp.all(jnp.isfinite(rpm)) & jnp.all(jnp.isfinite(euler)) & jnp.all(jnp.isfinite(v_air))
    )
    span = sur.box_hi - sur.box_lo
    tol = 1e-9 * jnp.maximum(span, 1.0)
    x_h, R_WH, rpm_g, euler_g = _frame(sur, rpm, euler, v_air)
    if sur.frame == "body":
        inside = jnp.all(
            (x_h[:4] >= sur.box_lo[:4] - tol[:4]) & (x_h[:4] <= sur.box_hi[:4] + tol[:4])
        )
        inside = inside & (jnp.sum(x_h[4:] ** 2) <= (sur.ball_radius * (1.0 + 1e-9)) ** 2)
        steady = jnp.asarray(True)  # no coordinate singularity to stay away from
    else:
        inside = jnp.all((x_h >= sur.box_lo - tol) & (x_h <= sur.box_hi + tol))
        # Near the airflow frame's singular sets the data's coordinates of the query swing
        # with millimetres per second of air, and a prediction with them: not in domain there.
        steady = airflow_frame_rate(euler_g, v_air, sur.hover_speed) <= MAX_FRAME_RATE
    return x_h, R_WH, finite & jnp.all(rpm_g >= 0) & inside & steady


def _check_half_turn(dataset: Dataset, vehicle: Vehicle) -> None:
    """``fit(half_turn=True)``'s checks: airflow-frame data of a vehicle that is its own image."""
    if dataset.frame != "airflow":
        raise ValueError(f"half_turn needs airflow-frame data, got frame {dataset.frame!r}")
    bad = vehicle.half_turn_asymmetries(levels=dataset.has_noise)
    # more with the levels than without: microphones off the axis, which data without need not
    hint = " (data without levels need no microphones: generate them with noise: false)"
    if bad:
        raise ValueError(
            f"half_turn: vehicle {vehicle.name!r} is not its own image under a half turn about "
            f"its z axis: {'; '.join(bad)}"
            + (hint if len(bad) > len(vehicle.half_turn_asymmetries()) else "")
        )


def _rotated_variance(R_out, v):
    """Per-output variances ``v`` of the GP's frame in the output frame: ``diag(R diag(d)
    Rᵀ)`` of the force's and the torque's (independent components), the levels' as they are."""
    rot_var = lambda d: jnp.einsum("ij,j,ij->i", R_out, d, R_out)  # noqa: E731
    return jnp.concatenate([rot_var(v[:3]), rot_var(v[3:6]), v[6:]])


@highest
def _predict_in_wind(sur, wind, rpm, euler, v_air, with_var: bool, body: bool) -> Prediction:
    """A model that tracks a wind state ``g ~ N(ḡ, P_g)`` (:func:`gpg.flight.gusts`): its
    prediction at ``v_air + ḡ``, the loads' variance with ``diag(J P_g Jᵀ)`` added (``J`` the
    loads' derivative in the air velocity there, in the output frame)."""
    mean, cov = (jnp.asarray(a).astype(v_air.dtype) for a in wind)
    still = eqx.tree_at(lambda s: s.model, sur, sur.model.without_wind())
    p = predict_state(still, rpm, euler, v_air + mean, with_var, body=body)
    if not with_var:
        return p

    def loads(g):
        q = predict_state(still, rpm, euler, v_air + g, False, body=body)
        return jnp.concatenate([q.force, q.torque])

    J = jax.jacfwd(loads)(mean)
    extra = jnp.einsum("ia,ab,ib->i", J, cov, J)
    variance = jnp.concatenate([p.variance[:6] + extra, p.variance[6:]])
    in_domain = p.in_domain & jnp.all(jnp.isfinite(extra))
    return Prediction(force=p.force, torque=p.torque, levels=p.levels, variance=variance,
                      in_domain=in_domain)  # fmt: skip


class SurrogateAero(AeroModel):
    """A :class:`Surrogate` as the aerodynamics of :class:`gpg.quadrotor.dynamics.Quadrotor`
    (mean prediction, world frame); body rates are not among its inputs."""

    surrogate: Surrogate

    def wrench(self, rpm: RotorSpeeds, R_WB: Rotation, v_air: Vector3, omega: Vector3) -> Wrench:
        """The surrogate's mean prediction as the aerodynamics of the rigid body.

        Args:
            rpm: (4,) rotor speeds.
            R_WB: (3, 3) attitude, body to world.
            v_air: (3,) world-frame air velocity, m/s.
            omega: body rates, not read (the surrogate does not take them).

        Returns:
            The world-frame force and torque, the levels and ``in_domain``.
        """
        p = predict_state(self.surrogate, rpm, euler_from_R(R_WB), v_air, False)
        return Wrench(p.force, p.torque, p.levels, p.in_domain)


@lru_cache(maxsize=32)
def _realtime_fn(treedef, with_var: bool):
    def fn(leaves, rpm, euler, v_air):
        return predict_state(
            jax.tree_util.tree_unflatten(treedef, leaves), rpm, euler, v_air, with_var
        )

    return jax.jit(fn)


# Plain jax.jit: every leaf of a Surrogate is an array, and jax.jit dispatches a call faster
# than eqx.filter_jit, which matters for a prediction this short (docs/measurements.md).
@partial(jax.jit, static_argnums=(4,))
def _predict(sur: Surrogate, rpm, euler, v_air, with_var: bool) -> Prediction:
    return predict_state(sur, rpm, euler, v_air, with_var)


@partial(jax.jit, static_argnums=(4,))
def _predict_body(sur: Surrogate, rpm, R, v_b, with_var: bool) -> Prediction:
    return predict_state(sur, rpm, euler_from_R(R), matvec(R, v_b), with_var, body=True)


@jax.jit
@highest
def _variance_parts(sur: Surrogate, rpm, euler, v_air) -> dict[str, Array]:
    sur, rpm, euler, v_air = _in_own_dtype(sur, rpm, euler, v_air)

    def one(r, e, v):
        x_h, R_WH, _ = _inputs(sur, r, e, v)
        _, var = sur.model.mean_var_one(sur.normalizer.x(x_h))
        parts = sur.model.variance_parts(var)
        return {k: _rotated_variance(R_WH, p * sur.normalizer.y_std**2) for k, p in parts.items()}

    return jax.vmap(one)(rpm, euler, v_air)


@partial(jax.jit, static_argnums=(4, 5))
def _predict_batch(sur: Surrogate, rpm, euler, v_air, with_var: bool, chunk: int) -> Prediction:
    def one(r, e, v):
        return predict_state(sur, r, e, v, with_var)

    n = rpm.shape[0]
    if n <= chunk:
        return jax.vmap(one)(rpm, euler, v_air)
    # Chunks by hand (pad to whole chunks, vmap each in lax.map): lax.map's own batch_size
    # fails on outputs of size zero, i.e. on every dataset without noise outputs.
    pad = (-n) % chunk

    def chunks(a):
        a = jnp.concatenate([a, jnp.broadcast_to(a[-1:], (pad, *a.shape[1:]))])
        return a.reshape(-1, chunk, *a.shape[1:])

    out = jax.lax.map(
        lambda args: jax.vmap(one)(*args), tuple(chunks(a) for a in (rpm, euler, v_air))
    )
    # Explicit sizes: reshape(-1, 0) cannot infer -1 for the empty noise outputs.
    return jax.tree.map(lambda o: o.reshape(o.shape[0] * o.shape[1], *o.shape[2:])[:n], out)
