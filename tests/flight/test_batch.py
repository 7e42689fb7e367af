"""gpg.flight.label_logs: a directory of CSV and ULog logs read and labelled across processes
and on a Dask cluster, the labels those of label() one log at a time whatever the workers, a
broken log named with its error and the others labelled."""

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from gpg.flight import FlightLogWarning, LabelledLogs, label, label_logs, read_csv, write_csv
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import load_vehicle
from tests.flight.flights import consistent_flight

ULOG = Path(__file__).parents[1] / "data" / "flight" / "px4_sitl_hop.ulg"
FIELDS = ("t", "rpm", "euler", "v_air", "force", "torque", "force_var", "torque_var")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Three consistent CSV logs, the PX4 log, and a CSV broken in its fourth line; the
    vehicle and M every log is labelled with."""
    root = tmp_path_factory.mktemp("logs")
    for i in range(3):
        write_csv(consistent_flight(n=1200, rate=100.0, seed=i, name=f"f{i}"), root / f"f{i}.csv")
    shutil.copy(ULOG, root / "px4.ulg")
    text = (root / "f0.csv").read_text().splitlines()
    text[3] = text[3] + ",1.0"  # one field too many: refused by read_csv
    (root / "broken.csv").write_text("\n".join(text) + "\n")
    (root / "notes.txt").write_text("not a log")
    veh = load_vehicle("sui_endurance")
    M = SimpleModel.from_vehicle(veh, float(veh.weight) / (4 * 3000.0**2), 1e-9)
    return root, veh, {"reference": M, "rate": 5.0, "source": "imu"}


def _quiet(fn, *a, **kw):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        out = fn(*a, **kw)
    return out, [str(w.message) for w in seen]


@pytest.fixture(scope="module")
def serial(setup):
    root, veh, opts = setup
    return _quiet(label_logs, root, veh, workers=1, progress=False, **opts)


def test_one_worker_is_label_one_log_at_a_time(setup, serial):
    """In this process, each log's labels are label(read(path)) exactly; the broken log is
    named with its error, the text file not read, the PX4 log read by its suffix; each log's
    warnings are raised again with its path and kept."""
    root, veh, opts = setup
    out, said = serial
    assert isinstance(out, LabelledLogs)
    names = [Path(p).name for p in out.labels]
    assert names == ["f0.csv", "f1.csv", "f2.csv", "px4.ulg"]  # sorted, the failed one absent
    assert list(map(lambda p: Path(p).name, out.failed)) == ["broken.csv"]
    err = out.failed[str(root / "broken.csv")]
    assert err.startswith("ValueError:") and "line 4" in err, err
    assert "1 failed" in out.report() and "broken.csv: ValueError" in out.report()
    assert len(out.parts()) == 4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FlightLogWarning)
        direct = label(read_csv(root / "f1.csv"), veh, **opts)
    got = out.labels[str(root / "f1.csv")]
    for f in FIELDS:
        assert np.array_equal(getattr(got, f), getattr(direct, f)), f
    ulog = str(root / "px4.ulg")
    assert ulog in out.warned
    assert any(s.startswith(f"{ulog}: ") for s in said)  # raised again, with its path


@pytest.mark.parametrize("workers", [2])
def test_the_labels_do_not_depend_on_the_workers(setup, serial, workers):
    """Two spawned processes give the same labels bit for bit, the same failures and the
    same warnings, in the same order."""
    root, veh, opts = setup
    out, _ = _quiet(label_logs, root, veh, workers=workers, progress=False, **opts)
    ref = serial[0]
    assert list(out.labels) == list(ref.labels) and out.failed == ref.failed
    assert out.warned == ref.warned
    for name, lab in ref.labels.items():
        for f in FIELDS:
            assert np.array_equal(getattr(out.labels[name], f), getattr(lab, f)), (name, f)


def test_on_a_dask_cluster(setup, serial):
    """A Dask client (an in-process cluster here: the same scheduler API as a remote one)
    labels the logs as one worker does."""
    distributed = pytest.importorskip("distributed")
    root, veh, opts = setup
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2,
                            dashboard_address=None) as client:  # fmt: skip
        out, _ = _quiet(label_logs, root, veh, client=client, progress=False, **opts)
    ref = serial[0]
    assert list(out.labels) == list(ref.labels) and out.failed == ref.failed
    for name, lab in ref.labels.items():
        assert np.array_equal(out.labels[name].force, lab.force), name


@pytest.mark.parametrize(
    "logs, kw, message",
    [
        ("missing_dir", {}, "is not a directory"),
        ("empty_dir", {}, "no .csv or .ulg files"),
        (["notes.txt"], {}, "is neither .csv nor .ulg"),
        (["gone.csv"], {}, "does not exist"),
        (["f0.csv", "f0.csv"], {}, "given twice"),
        ([], {}, "non-empty list"),
        (["f0.csv"], {"rate_hz": 5.0}, "unknown label option"),
        (["f0.csv"], {"rate": "5"}, "rate must be a number"),
        (["f0.csv"], {"source": "gps"}, "source must be"),
        (["f0.csv"], {"workers": 0}, "workers must be a positive integer"),
        (["f0.csv"], {"client": object()}, "client must be a dask.distributed.Client"),
        (["f0.csv"], {"csv_format": {"world": "nwu"}}, "csv_format must be a CsvFormat"),
    ],
)
def test_bad_arguments_named_before_any_log_is_read(setup, tmp_path, logs, kw, message):
    root, veh, opts = setup
    (tmp_path / "empty_dir").mkdir()
    if isinstance(logs, str):
        logs = tmp_path / logs
    else:
        logs = [root / p for p in logs]
    with pytest.raises(ValueError, match=message):
        label_logs(logs, veh, progress=False, **{**opts, **kw})
