"""Real flights: flight logs in, loads from measured motion, the simulator-trained surrogate
corrected by flights, adaptation while flying (docs: "From flight logs").

* :func:`read_csv` / :func:`read_ulog` read a flight into a :class:`FlightLog` (gpg's frames
  and units, checked); :class:`CsvFormat` says how a CSV differs from them; :func:`consistency`
  checks its signals against each other (each an :class:`Agreement`; the readers refuse a log
  whose signals disagree).
* :func:`label` turns measured motion into force and torque labels with their noise
  (:class:`Labels`; :func:`estimate_delay` the rotor speeds' lag from many logs at once),
  :func:`label_logs` a directory of logs across processes or on a Dask
  cluster (:class:`LabelledLogs`); :class:`MotorCurve` and :func:`calibrate_simple` turn
  commands into rotor speeds and fit ``M`` to a hover.
* :func:`correct` corrects a fitted :class:`~gpg.Surrogate` by labels (a :class:`Corrected`
  model: the prior's mean, scaled, plus values-only discrepancy GPs); :func:`track` follows
  its physical basis's coefficients online (a Kalman filter, its drift fitted by
  :func:`fit_drift`, any drift scored alike by :func:`score_drift`; with :func:`gusts`, the
  wind's deviation from the log's too),
  :func:`adapt` adds an inducing-point term instead (its forgetting time fitted by
  :func:`fit_forgetting`), :func:`adapt_bank` several of them mixed by their predictions
  made ahead (a :class:`Bank`; its weights' forgetting fitted by :func:`fit_bank`);
  :func:`update` and
  :func:`online_step` update either label by label at a fixed cost, :func:`prequential` runs
  a flight through them.
* :func:`identify` finds the vehicle's physical parameters from labels (an
  :class:`Identification`, written as a vehicle file, its simulator prior regenerated);
  :func:`estimate_wind` and :func:`with_wind` give labels the wind where none was logged;
  :mod:`gpg.flight.basis` is the correction's physical basis.
* :mod:`gpg.flight.synthetic` flies a vehicle with known truth through realistic sensors.
"""

from gpg.flight import basis, synthetic
from gpg.flight.bank import Bank, adapt_bank
from gpg.flight.batch import LabelledLogs, label_logs
from gpg.flight.correction import (
    Corrected,
    Online,
    adapt,
    base,
    correct,
    online_state,
    online_step,
    update,
    update_jit,
    with_online,
)
from gpg.flight.forgetting import BankFit, Forgetting, fit_bank, fit_forgetting
from gpg.flight.identify import Identification, IdentificationWarning, identify
from gpg.flight.kinematics import Agreement, consistency
from gpg.flight.labels import (
    Labels,
    MotorCurve,
    calibrate_simple,
    estimate_delay,
    hover_samples,
    label,
)
from gpg.flight.log import CsvFormat, FlightLog, FlightLogWarning, read_csv, write_csv
from gpg.flight.tracking import (
    Drift,
    Prequential,
    Tracker,
    default_drift,
    fit_drift,
    gusts,
    prequential,
    score_drift,
    track,
)
from gpg.flight.ulog import read_ulog
from gpg.flight.wind import WindEstimate, WindWarning, estimate_wind, with_wind

__all__ = [
    "Agreement",
    "Bank",
    "BankFit",
    "Corrected",
    "consistency",
    "Drift",
    "Forgetting",
    "Identification",
    "IdentificationWarning",
    "WindEstimate",
    "WindWarning",
    "basis",
    "estimate_wind",
    "identify",
    "with_wind",
    "CsvFormat",
    "FlightLog",
    "FlightLogWarning",
    "Labels",
    "LabelledLogs",
    "MotorCurve",
    "Online",
    "Prequential",
    "Tracker",
    "adapt",
    "adapt_bank",
    "base",
    "calibrate_simple",
    "correct",
    "default_drift",
    "estimate_delay",
    "fit_bank",
    "fit_drift",
    "fit_forgetting",
    "gusts",
    "hover_samples",
    "label",
    "label_logs",
    "online_state",
    "online_step",
    "prequential",
    "read_csv",
    "read_ulog",
    "score_drift",
    "synthetic",
    "track",
    "update",
    "update_jit",
    "with_online",
    "write_csv",
]
