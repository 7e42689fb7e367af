"""From a :class:`Dataset` to the GP's targets, and back (paper, Section "Data Processing").

1. Residuals against the simplified model ``M``: ``y_c = y_aero − y_M``,
   ``J_c = J_aero − J_M``; the noise outputs are kept as they are (``M`` has no noise).
2. Normalisation (Eqs. normalize_x/y/g): inputs min-max to [−1, 1], outputs z-scored,
   gradient ``∂_j y_m`` scaled by ``(max−min)_j / 2 / std(y_m)``.
3. Gradient noise ``λ_j² = s · Var(∂_j Ỹ)`` over all points and outputs (``s = 0.3``).

Every transform has an exact inverse on :class:`Normalizer`, so predictions return in
physical units.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg.data.convert import _R_batch
from gpg.data.dataset import Dataset
from gpg.names import GRAD_DIMS
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise
from gpg.quadrotor.vehicle import Vehicle

__all__ = [
    "FittedCoefficientsWarning",
    "Normalizer",
    "Training",
    "normalised_gradients",
    "prepare",
    "residuals",
    "restore",
    "simple_model_for",
]


class Normalizer(eqx.Module):
    """Input box, output mean/std, and the gradient scaling built from them.

    A constant input (``max = min``) or output (``std = 0``) gets scale 1, so a dataset that
    never varies airspeed still normalises (and the GP simply learns nothing along it).
    """

    x_lo: Float[Array, " D"]
    x_hi: Float[Array, " D"]
    y_mean: Float[Array, " M"]
    y_std: Float[Array, " M"]
    grad_dims: tuple[int, ...] = eqx.field(static=True, default=GRAD_DIMS)

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, grad_dims: Sequence[int] = GRAD_DIMS) -> Normalizer:
        """The normaliser of a training set: its input box and its outputs' mean and spread.

        Args:
            x: (N, D) inputs in dataset units.
            y: (N, M) outputs (residuals against ``M``).
            grad_dims: the input dims the gradient columns are taken along.

        Returns:
            The :class:`Normalizer`; a constant input gets the box ``[value, value + 2]``
            (half-range 1), a constant output the scale 1.
        """
        lo, hi = x.min(0), x.max(0)
        hi = np.where(hi > lo, hi, lo + 2.0)  # constant input: half-range 1 about lo + 1
        std = y.std(0)
        return cls(
            x_lo=jnp.asarray(lo),
            x_hi=jnp.asarray(hi),
            y_mean=jnp.asarray(y.mean(0)),
            y_std=jnp.asarray(np.where(std > 0, std, 1.0)),
            grad_dims=tuple(grad_dims),
        )

    @property
    def half_range(self) -> Float[Array, " D"]:
        return 0.5 * (self.x_hi - self.x_lo)

    @eqx.filter_jit
    def x(self, x: Float[ArrayLike, "... D"]) -> Float[Array, "... D"]:
        """Inputs normalised to the box [−1, 1] (Eq. normalize_x).

        Args:
            x: (..., D) inputs in dataset units.

        Returns:
            ``2 (x − min)/(max − min) − 1``, same shape.
        """
        return (jnp.asarray(x) - self.x_lo) / self.half_range - 1.0

    @eqx.filter_jit
    def x_inv(self, xn: Float[ArrayLike, "... D"]) -> Float[Array, "... D"]:
        """Normalised inputs back in dataset units, the inverse of :meth:`x`.

        Args:
            xn: (..., D) normalised inputs.

        Returns:
            The inputs in dataset units, same shape.
        """
        return (jnp.asarray(xn) + 1.0) * self.half_range + self.x_lo

    @eqx.filter_jit
    def y(self, y: Float[ArrayLike, "... M"]) -> Float[Array, "... M"]:
        """Outputs z-scored (Eq. normalize_y).

        Args:
            y: (..., M) outputs in physical units (residuals against ``M``).

        Returns:
            ``(y − mean)/std``, same shape.
        """
        return (jnp.asarray(y) - self.y_mean) / self.y_std

    @eqx.filter_jit
    def y_inv(self, yn: Float[ArrayLike, "... M"]) -> Float[Array, "... M"]:
        """Normalised outputs back in physical units, the inverse of :meth:`y`.

        Args:
            yn: (..., M) normalised outputs.

        Returns:
            ``yn · std + mean``, same shape.
        """
        return jnp.asarray(yn) * self.y_std + self.y_mean

    def grad_scale(self) -> Float[Array, "M G"]:
        """The factors that normalise gradients (Eq. normalize_g).

        Returns:
            (M, G): ``(max−min)_j / 2 / std(y_m)`` for output ``m`` and gradient dim ``j``.
        """
        return self.half_range[jnp.asarray(self.grad_dims)][None, :] / self.y_std[:, None]

    @eqx.filter_jit
    def grad(self, J: Float[ArrayLike, "... M G"]) -> Float[Array, "... M G"]:
        """Gradients along the input dims normalised (Eq. normalize_g, :meth:`grad_scale`).

        Args:
            J: (..., M, G) gradients in dataset units.

        Returns:
            The normalised gradients, same shape.
        """
        return jnp.asarray(J) * self.grad_scale()

    @eqx.filter_jit
    def grad_inv(self, Jn: Float[ArrayLike, "... M G"]) -> Float[Array, "... M G"]:
        """Normalised gradients back in dataset units, the inverse of :meth:`grad`.

        Args:
            Jn: (..., M, G) normalised gradients.

        Returns:
            The gradients in dataset units, same shape.
        """
        return jnp.asarray(Jn) / self.grad_scale()

    def var_inv(self, var: Float[ArrayLike, "..."]) -> Float[Array, "... M"]:
        """Per-output variance in physical units from the shared latent variance.

        One kernel serves all outputs, so each output's variance is the latent one scaled by
        that output's ``std²``.

        Args:
            var: (...) latent variances in normalised units.

        Returns:
            (..., M) the variance of each output.
        """
        return jnp.asarray(var)[..., None] * self.y_std**2


@dataclass(frozen=True)
class Training:
    """The GP's view of a dataset: normalised residual targets and what produced them.

    ``X`` (N, 8), ``Y`` (N, M), ``dY`` (N, M, 7) or None, ``X_raw``/``Y_raw`` the normalised
    raw 8X samples or None; ``simple`` is ``M`` and ``noise_model`` ``M_noise`` (None when unused).
    """

    X: np.ndarray
    Y: np.ndarray
    dY: np.ndarray | None
    X_raw: np.ndarray | None
    Y_raw: np.ndarray | None
    normalizer: Normalizer
    simple: SimpleModel | None
    output_names: tuple[str, ...]
    noise_model: SimpleNoise | None = None
    frame: str = "airflow"  # the data's inputs (gpg.names.FRAMES): where M's attitude comes from
    # (N, G, G): the directions of the gradient columns of dY in the normalised inputs, each of
    # unit length (gpg.gp.gram.row_directions), for data with Dataset.grad_dirs; else None
    bases: np.ndarray | None = None


class FittedCoefficientsWarning(UserWarning):
    """``M``'s coefficients were fitted from the data: neither the vehicle nor the dataset
    gave them. The message holds the values."""


def simple_model_for(ds: Dataset, vehicle: Vehicle) -> SimpleModel:
    """The simplified model ``M`` for a dataset and its vehicle.

    ``P_F``, ``T_z`` come from the vehicle file's ``simple_model`` section, else from the
    dataset's metadata (written by the generator), else a least-squares fit to the data
    itself (``−F_zB ≈ P_F Σr²``, ``τ_zB ≈ −T_z Σ d_i r_i²``) with a
    :class:`FittedCoefficientsWarning` stating the values.

    Args:
        ds: the dataset (its metadata, or its cases for the fit).
        vehicle: the vehicle: rotor layout, spins, and perhaps the coefficients.

    Returns:
        The :class:`~gpg.quadrotor.simple_model.SimpleModel`.
    """
    if vehicle.thrust_coefficient is not None:
        return SimpleModel.from_vehicle(
            vehicle, vehicle.thrust_coefficient, vehicle.torque_coefficient
        )
    coeffs = ds.meta.get("simple_model")
    if coeffs is not None:
        return SimpleModel.from_vehicle(vehicle, coeffs["P_F"], coeffs["T_z"])
    R = np.asarray(_R_batch(_m_inputs(ds.frame, ds.x)[:, 4:7]))
    F_B = np.einsum("nji,nj->ni", R, ds.y_aero[:, :3])
    tau_B = np.einsum("nji,nj->ni", R, ds.y_aero[:, 3:])
    r2 = ds.x[:, :4] ** 2
    spin = np.asarray(vehicle.spin)
    s_thrust, s_yaw = r2.sum(1), r2 @ spin
    P_F = float(np.sum(-F_B[:, 2] * s_thrust) / np.sum(s_thrust**2))
    T_z = float(-np.sum(tau_B[:, 2] * s_yaw) / max(np.sum(s_yaw**2), 1e-300))
    warnings.warn(
        f"vehicle {vehicle.name!r} gives no simple_model coefficients and the dataset records "
        f"none: fitted from the data, P_F = {P_F:.4g} N/rpm², T_z = {T_z:.4g} N·m/rpm² "
        "(put them in the vehicle file's simple_model section to fix them)",
        FittedCoefficientsWarning,
        stacklevel=2,
    )
    return SimpleModel.from_vehicle(vehicle, P_F, T_z)


def residuals(
    ds: Dataset, simple: SimpleModel | None, noise_model: SimpleNoise | None = None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A dataset's outputs, gradients and raw samples with the simplified models subtracted.

    ``M`` comes off the six aerodynamic outputs, their gradients (along the data's gradient
    columns, :attr:`Dataset.grad_dirs`) and their raw samples; in the body frame ``M``
    depends on the rotor speeds alone. ``M_noise`` comes off the three levels the same way.

    Args:
        ds: the dataset.
        simple: ``M``; None leaves the aerodynamic outputs as they are.
        noise_model: ``M_noise``; None (or a dataset without levels) leaves the levels.

    Returns:
        ``(y, J, y_raw)``: (N, M) outputs, (N, M, 7) gradients or None, (8N, M) raw samples
        or None; copies, the dataset is not changed.
    """
    y, J = ds.y.copy(), None if ds.jac is None else ds.jac.copy()
    y_raw = None if ds.y_raw is None else ds.y_raw.copy()

    def along(JM):  # a model's Jacobian along the data's gradient columns
        return JM if ds.grad_dirs is None else np.einsum("nmh,ngh->nmg", JM, ds.grad_dirs)

    if simple is not None:
        yM, JM = (np.asarray(a) for a in simple.batch(_m_inputs(ds.frame, ds.x)))
        if ds.frame == "body":  # M in the body frame depends on the rotor speeds alone
            JM = JM.copy()
            JM[:, :, 4:] = 0.0
        y[:, :6] -= yM
        if J is not None:
            J[:, :6] -= along(JM)
        if y_raw is not None:
            y_raw[:, :6] -= np.asarray(simple.values(_m_inputs(ds.frame, ds.x_raw)))
    if noise_model is not None and ds.has_noise:
        yN, JN = (np.asarray(a) for a in noise_model.batch(ds.x))
        y[:, 6:9] -= yN
        if J is not None:
            J[:, 6:9] -= along(JN[:, :, : J.shape[2]])
        if y_raw is not None:
            y_raw[:, 6:9] -= np.asarray(noise_model.batch(ds.x_raw)[0])
    return y, J, y_raw


def _m_inputs(frame: str, x: np.ndarray) -> np.ndarray:
    """``x_M = (r1..r4, yaw, pitch, roll)`` of :class:`SimpleModel` for inputs ``x`` in
    ``frame``: the body frame's outputs are already in the body frame (identity attitude)."""
    if frame == "airflow":
        return x[:, :7]
    return np.concatenate([x[:, :4], np.zeros((x.shape[0], 3))], axis=1)


def prepare(
    ds: Dataset,
    simple: SimpleModel | None,
    noise_model: SimpleNoise | None = None,
) -> Training:
    """The GP's view of a dataset: residuals against the simplified models, normalised.

    The normalisation's statistics come from the base points (the gradient noise ``λ²`` is
    the model's: :func:`gpg.models.initial_hyper`). Cases that share an input are warned
    about (:meth:`Dataset.repeated_inputs`), not refused.

    Args:
        ds: the dataset.
        simple: ``M``, subtracted from the aerodynamic outputs; None to keep them.
        noise_model: ``M_noise``, subtracted from the levels; None to keep them.

    Returns:
        The :class:`Training`: normalised inputs, targets, gradients and raw samples, and the
        normaliser and models that produced them.

    Raises:
        ValueError: if an output or input overflows float64 when standardised (naming it).
    """
    warn_repeated_inputs(ds)
    y, J, y_raw = residuals(ds, simple, noise_model)
    norm = Normalizer.fit(ds.x, y)
    X = np.asarray(norm.x(ds.x))
    Y = np.asarray(norm.y(y))
    dY, bases = (None, None) if J is None else normalised_gradients(norm, J, ds.grad_dirs)
    X_raw = Y_raw = None
    if ds.has_raw:
        X_raw = np.asarray(norm.x(ds.x_raw))
        Y_raw = np.asarray(norm.y(y_raw))
    _check_standardised(ds.output_names, y, norm, X, Y, dY, X_raw, Y_raw)
    return Training(
        X=X,
        Y=Y,
        dY=dY,
        X_raw=X_raw,
        Y_raw=Y_raw,
        normalizer=norm,
        simple=simple,
        output_names=ds.output_names,
        noise_model=noise_model if ds.has_noise else None,
        frame=ds.frame,
        bases=bases,
    )


def normalised_gradients(
    norm: Normalizer, J: Float[np.ndarray, "N M G"], dirs: Float[np.ndarray, "N G G"] | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The GP's gradient targets, and their directions when the columns are directional.

    Args:
        norm: the training set's normaliser.
        J: (N, M, G) gradients in dataset units (residuals against ``M``).
        dirs: (N, G, G) the direction of each gradient column (:attr:`Dataset.grad_dirs`),
            or None for derivatives along the inputs themselves.

    Returns:
        ``(dY, bases)``: without ``dirs``, ``(Normalizer.grad(J), None)``; with them, the
        derivatives along unit directions of the normalised inputs and those directions
        (:func:`normalised_directions`).

    Raises:
        ValueError: if a zero direction carries a gradient (:func:`normalised_directions`).
    """
    if dirs is None:
        return np.asarray(norm.grad(J)), None
    return normalised_directions(norm, J, dirs)


def normalised_directions(
    norm: Normalizer, J: Float[np.ndarray, "N M G"], dirs: Float[np.ndarray, "N G G"]
) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives ``J[i, :, g]`` along the directions ``dirs[i, g]`` (dataset units) as the
    GP's rows: the direction in the normalised inputs, ``d̃ = d / h`` (``h`` the half-ranges),
    scaled to unit length, and the derivative along it, ``J / (|d̃| std(y))``. A coordinate
    direction gives :meth:`Normalizer.grad`'s row exactly; a zero direction (no derivative)
    keeps a unit one with its values, which must then be NaN (not run)."""
    h = np.asarray(norm.half_range)[np.asarray(norm.grad_dims)]
    d = np.asarray(dirs) / h[None, None, :]
    length = np.linalg.norm(d, axis=2)  # (N, G)
    zero = length == 0.0
    if np.any(zero & ~np.isnan(J[:, 0, :])):
        rows = np.flatnonzero(np.any(zero & ~np.isnan(J[:, 0, :]), axis=1))[:10].tolist()
        raise ValueError(
            f"grad_dirs has a zero direction with a gradient in row(s) {rows}: a derivative "
            "needs a direction (NaN marks one that was not run)"
        )
    length = np.where(zero, 1.0, length)
    d = np.where(zero[:, :, None], np.eye(d.shape[1])[None], d / length[:, :, None])
    dY = J / (length[:, None, :] * np.asarray(norm.y_std)[None, :, None])
    return dY, d


def warn_repeated_inputs(ds: Dataset) -> None:
    """A ``UserWarning`` for cases that share an input (:meth:`Dataset.repeated_inputs`):
    how many, which rows, and what the fit does with them. Repeats may be intended (repeated
    runs of a noisy experiment), so this warns rather than refuses."""
    conflicting, identical = ds.repeated_inputs()
    if conflicting:
        spread = max(float(np.max(np.ptp(ds.y[g], axis=0))) for g in conflicting)
        shown = [g.tolist() for g in conflicting[:5]]
        more = f" (and {len(conflicting) - 5} more)" if len(conflicting) > 5 else ""
        warnings.warn(
            f"{len(conflicting)} group(s) of cases share an identical input but have different "
            f"outputs or gradients: rows {shown}{more}, output spread up to {spread:.3g}. No "
            "function passes through both: a fitted value noise ν² grows to explain the spread "
            "(every prediction's variance with it), a fixed small ν² leaves the solve "
            "ill-conditioned and the mean at their average. Drop or average repeats that are "
            "mistakes; keep them if they are repeated noisy runs.",
            UserWarning,
            stacklevel=3,
        )
    if identical:
        shown = [g.tolist() for g in identical[:5]]
        warnings.warn(
            f"{len(identical)} group(s) of cases are exact copies (same input and outputs): "
            f"rows {shown}; they add nothing but cost and are kept.",
            UserWarning,
            stacklevel=3,
        )


def _check_standardised(names, y, norm, X, Y, dY, X_raw, Y_raw) -> None:
    """Finite data can still overflow in the standardisation (a value of 1e308 squares to
    inf): a ``ValueError`` naming the output or input, never a model that answers NaN."""
    with np.errstate(all="ignore"):
        std, mean = np.asarray(norm.y_std), np.asarray(norm.y_mean)
        for m, name in enumerate(names):
            if not (np.isfinite(std[m]) and np.isfinite(mean[m])) or not np.all(
                np.isfinite(Y[:, m])
            ):
                big = float(np.max(np.abs(y[:, m])))
                raise ValueError(
                    f"output {name!r} cannot be standardised: its mean or spread overflows "
                    f"float64 (largest |{name}| = {big:.3g}, after subtracting the simplified "
                    "model); check the data's units and outliers"
                )
        for what, arr in (
            ("inputs", X),
            ("gradients", None if dY is None else dY[~np.isnan(dY)]),  # NaN: not run
            ("raw inputs", X_raw),
            ("raw outputs", Y_raw),
        ):
            if arr is not None and not np.all(np.isfinite(arr)):
                raise ValueError(
                    f"the {what} overflow when normalised (values too large for float64); "
                    "check the data's units and outliers"
                )


def restore(
    training: Training, x: Float[ArrayLike, "N 8"], y_norm: Float[ArrayLike, "N M"]
) -> np.ndarray:
    """Normalised outputs back in physical units, the inverse of :func:`prepare`.

    Args:
        training: the :class:`Training` the outputs were normalised by.
        x: (N, 8) the cases' inputs in dataset units ((N, 7) in the body frame), where ``M``
            is evaluated.
        y_norm: (N, M) normalised outputs (residuals).

    Returns:
        (N, M) outputs in physical units: de-normalised, with ``M`` (and ``M_noise``) added
        back.
    """
    y = np.asarray(training.normalizer.y_inv(y_norm)).copy()
    if training.simple is not None:
        x_m = _m_inputs(training.frame, np.asarray(x))
        y[:, :6] += np.asarray(training.simple.values(jnp.asarray(x_m)))
    if training.noise_model is not None and y.shape[1] > 6:
        y[:, 6:9] += np.asarray(training.noise_model.batch(x)[0])
    return y
