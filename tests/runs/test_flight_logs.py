"""``experiments.flight_logs``, the sim-to-real benchmark, composed with Hydra: its options
checked before any work (fast), the whole run at a smoke size (slow; its pieces have fast tests
in tests/flight)."""

import json

import numpy as np
import pytest

from experiments.runs import flight_logs
from gpg import checkpoint
from gpg.flight.synthetic import perturbed
from tests.helpers import compose_plain, finite_numbers

SMOKE = [
    "data=smoke",
    "data.chunk=32",
    "flights.flight_s=10",
    "flights.train_s=20",
    "flights.test=1",
    "flights.test_s=10",
    "seconds=[5,10,20]",
    "default_seconds=10",
    "adapt.flight_s=15",
    "adapt.offline_s=10",
    "adapt.check_s=5",
    "adapt.stream_s=20",
    "progress=false",
    "correct.exact_labels=150",  # the curve's last point (200 labels) through inducing inputs
    "correct.inducing=40",
    "correct.compare_thinned=150",
    "correct.compare_exact_at=20",
]


@pytest.mark.parametrize(
    "bad, message",
    [
        (["default_seconds=7"], "default_seconds 7 must be one of seconds"),
        (["seconds=[5,10,60]", "default_seconds=10"], "seconds go to 60.0 s"),
        (["progress=maybe"], "progress must be true or false"),
        (["scenario=harder"], "scenario must be 'nominal' or 'hard'"),
        (["scenario=hard", "hard.train_kinds=[eight,loop]"], "hard.train_kinds must name"),
        (["scenario=hard", "hard.train_kinds=[]"], "hard.train_kinds must name"),
        (["scenario=hard", "hard.train_kinds=[walk]"], "calm figure-eight's hover"),
        (["scenario=hard", "hard.train_winds=[4.0,8.0]"], "calm figure-eight's hover"),
    ],
)
def test_options_checked_before_any_work(bad, message, tmp_path):
    cfg = compose_plain("flight_logs", SMOKE + bad)
    with pytest.raises(ValueError, match=message):
        flight_logs.run(cfg, tmp_path)
    assert not any(tmp_path.iterdir())  # nothing written


def test_hard_training_plan():
    """Each wind flown as each of ``hard.train_kinds`` in turn: the default is the plan (and so
    the seeds) of the runs before the option; figure-eights only repeat the eight."""
    from experiments.runs.flight_hard import training_plan

    h = compose_plain("flight_logs", ["scenario=hard"])["hard"]
    assert training_plan(h) == [(w, k) for w in (0.0, 4.0, 8.0) for k in ("eight", "walk")]
    h["train_kinds"] = ["eight", "eight"]
    assert training_plan(h) == [(w, "eight") for w in (0.0, 0.0, 4.0, 4.0, 8.0, 8.0)]


def test_label_offset_from_the_sensors():
    """``track.label_offset: sensors``: the accelerometer's bias times the mass for labels from
    the IMU, none from the velocity; a pair is taken as it is."""
    from gpg.flight.synthetic import Sensors

    s = Sensors(accel_bias=0.05)
    assert flight_logs.label_offset("sensors", s, 2.0, "imu") == pytest.approx((0.1, 0.0))
    assert flight_logs.label_offset("sensors", s, 2.0, "velocity") == (0.0, 0.0)
    assert flight_logs.label_offset([0.2, 0.01], s, 2.0, "imu") == (0.2, 0.01)


@pytest.mark.slow
def test_flight_logs_run(smoke_cache, tmp_path):
    cfg = compose_plain("flight_logs", [*SMOKE, f"cache_dir={smoke_cache}"])
    res = flight_logs.run(cfg, tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers(saved) and saved["config"]["default_seconds"] == 10
    assert [r["seconds"] for r in saved["curve"]] == [5.0, 10.0, 20.0]
    last = saved["curve"][-1]
    assert last["corrected_inducing"] == 40 and last["corrected_thinned_force_rmse"] > 0
    assert last["corrected_exact_force_rmse"] > 0 and last["corrected_exact_fit_s"] > 0
    assert saved["curve"][0]["corrected_inducing"] is None  # 50 labels: exact
    d = saved["default"]
    for key in ("sim_only", "corrected", "values_only", "values_only_m", "corrected_unscaled"):
        assert d[f"{key}_force_rmse"] > 0
    a = saved["adaptation"]
    for name in ("inducing", "tracked", "tracked_gusts"):
        c = a["cost"][name]
        assert c["bytes_start"] == c["bytes_end"] and c["median_ms"] > 0  # fixed memory
        assert len(a["models"][name]["windows"]) >= 2
    models = ("none", "inducing", "tracked", "tracked_gusts")
    assert {f"{m}_mse" for m in models} <= set(a["tests"][0])
    assert a["drift"]["source"] == "fitted"
    pooled = saved["labels"]["delay_pooled_s"]
    assert set(pooled) == {"2_flights"} and abs(pooled["2_flights"]) <= 0.1
    # the logs have an IMU: the band states its accelerometer's bias times the mass
    mass = float(perturbed(cfg["vehicle"], cfg["real"].get("changes") or {}).mass)
    assert a["drift"]["label_offset"] == pytest.approx([cfg["sensors"]["accel_bias"] * mass, 0])
    # every sample read too, scored at the same labels: the offline model's scores the same
    # (and with a drift fitted on every sample of the training flights)
    fit_stream = ("tracked_fit_stream", "tracked_gusts_fit_stream")
    assert a["stream_labels"] > a["stream_scored"]
    assert set(a["stream_models"]) == {*models, *fit_stream}
    assert a["stream_drift"]["labels"] > a["drift"]["labels"] and a["stream_drift"]["fit_s"] > 0
    assert all(r[f"stream_{m}_mse"] > 0 for r in a["tests"] for m in fit_stream)
    for r in a["tests"]:
        assert r["stream_scored"] == r["labels"] < r["stream_labels"]
        assert r["stream_none_mse"] == pytest.approx(r["none_mse"], rel=1e-9)
    for fig in ("error_vs_seconds", "force_along_flight"):
        assert (tmp_path / "figures" / f"{fig}.png").is_file()
    assert sorted(p.name for p in (tmp_path / "logs").glob("*.csv"))[0] == "test00.csv"
    sur = checkpoint.load(tmp_path / "corrected")
    assert sur.model_name.endswith("+flight")
    assert np.isfinite(res["targets"]["corrected_vs_sim_only"])


HARD = [
    "scenario=hard",
    "data=smoke",
    "data.chunk=32",
    "hard.data=smoke",
    "hard.flight_s=10",
    "hard.train_winds=[0.0,6.0]",
    "hard.test_wind=10.0",
    "hard.figure_eight.hold_s=3.0",
    "hard.identify.max_labels=120",
    "hard.identify.max_steps=15",
    "progress=false",
]


@pytest.mark.slow
def test_flight_logs_hard_scenario(smoke_cache, tmp_path):
    """The hard scenario at a smoke size: every model scored on both test winds, the
    identified vehicle written as a file the generator reads, the winds estimated."""
    from gpg.quadrotor.vehicle import load_vehicle

    cfg = compose_plain("flight_logs", [*HARD, f"cache_dir={smoke_cache}"])
    res = flight_logs.run(cfg, tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers(saved["tests"]) and [r["test"] for r in res["tests"]] == [
        "steady",
        "gust",
    ]
    for key in ("prior", "corrected_regression", "values_only", "identified_prior", "identified",
                "identified_rho", "identified_estimated_wind", "identified_true_air",
                "oracle", "oracle_mean_air"):  # fmt: skip
        assert res["tests"][0][f"{key}_mse"] > 0
    # the guide's band split into its terms, the gust's wind among them
    for r, wind in zip(res["tests"], ([], ["wind"]), strict=True):
        terms = ["basis", "discrepancy", "discrepancy_noise", "prior", *wind]
        every = r["identified_band_parts"]["all"]
        assert sorted(every) == sorted([*terms, "mse", "coverage95"])
        assert all(v >= 0 for p in every.values() for v in p)
        # the split's band is the score's: the same coverage
        assert every["coverage95"] == pytest.approx(r["identified_coverage95_components"])
    co = saved["coefficients"]
    assert co["identified"]["rho"] == [1.0] * 6 and co["identified_rho"]["rho"] != [1.0] * 6
    assert all(c >= 1.0 for m in co.values() for c in m["calibration"])  # only widened
    # the physical terms' prior chosen per output among the grid, by the winds held out
    for m in co.values():
        bp = m["basis_prior"]
        assert set(bp["factors"]) <= set(bp["grid"]) and len(bp["held_out_nlpd"]) == 6
        # the coefficients' spread between the winds held out: an sd per output and column
        spread = np.asarray(bp["coefficient_spread"])
        assert spread.shape[0] == 6 and np.all(spread >= 0) and np.any(spread > 0)
    load_vehicle(tmp_path / "identified_vehicle.yaml").require_generator()
    assert len(res["wind"]) == 4 and all(np.isfinite(w["rms_error"]) for w in res["wind"])
    assert set(res["identification"]["parameters"]) == set(cfg["hard"]["identify"]["free"])
    # the same flights with their rotor speeds logged: no motor curve, the ESC logs kept
    speeds = res["identification_with_speeds"]
    assert set(speeds["parameters"]) == set(cfg["hard"]["with_speeds"]["free"])
    assert not any(k.startswith("motor.") for k in speeds["parameters"])
    assert len(list((tmp_path / "logs").glob("train*_esc.csv"))) == 4
    # and the commands through a bench's curve, which keeps the file's motor lag
    bench = res["identification_with_bench_curve"]
    assert set(bench["parameters"]) == set(cfg["hard"]["bench_curve"]["free"])
    assert bench["curve"]["source"] == "speeds" and bench["curve"]["time_constant"] > 0
    assert len(bench["thrust_per_command"]["relative_error"]) == 3
    for ident in (res["identification"], speeds, bench):
        for k in ("thrust_coefficient", "torque_coefficient"):  # M's, with standard errors
            c = ident[k]
            assert c["truth"] > 0 and 0 < c["se_data"] <= c["se"] < c["identified"]
    ad = res["adaptation"]
    assert [r["test"] for r in ad["tests"]] == ["steady", "gust"] and finite_numbers(ad["tests"])
    assert ad["tracked_update"]["bytes_start"] == ad["tracked_update"]["bytes_end"]
    u = ad["tracked_gusts_update"]  # the wind state: fixed memory too
    assert u["bytes_start"] == u["bytes_end"] > ad["tracked_update"]["bytes_end"]
    gust = ad["tests"][1]
    assert gust["tracked_gusts_mse"] > 0 and gust["tracked_gusts_vertical_mse"] > 0
    # a spread per column fitted; uniform spreads swept and one spread fitted beside it, each
    # scored held out (the per-column fit highest: it nests them) and prequentially
    assert ad["drift"]["columns"] and len(ad["drift"]["spread"]) == len(ad["drift"]["columns"])
    assert isinstance(ad["one_spread"]["spread"], float)
    # the drift fitted on every sample of the training flights reads more rows than the
    # labels' over the same span
    assert ad["stream_drift"]["source"] == "fitted"
    assert ad["stream_drift"]["labels"] > ad["drift"]["labels"]
    # the inducing-point term's forgetting time and prior fitted on the same rows, the best
    # of its grid at least, read by the stream's term
    # (the shared band also with a pair per load output, at least as likely as the one pair,
    # and per output with each label predicted from the samples ten before it)
    assert set(ad["forgetting"]) == {"added", "shared", "shared_per_output",
                                     "shared_per_output_ahead10"}  # fmt: skip
    for name, fo in ad["forgetting"].items():
        assert fo["labels"] == ad["stream_drift"]["labels"] and fo["inducing"] <= 48
        assert fo["band"] == name.split("_")[0]
        assert fo["ahead"] == (10 if name.endswith("_ahead10") else 1)
        assert fo["log_likelihood"] >= max(ll for *_, ll in fo["grid"]) - 1e-9
    own = ad["forgetting"]["shared_per_output"]
    assert len(own["tau"]) == len(own["factor"]) == 6
    assert own["log_likelihood"] >= ad["forgetting"]["shared"]["log_likelihood"] - 1e-9
    for m in (
        "inducing_fitted",
        "inducing_fitted_shared",
        "inducing_fitted_shared_per_output",
        "inducing_fitted_shared_per_output_ahead10",
    ):
        assert all(r[f"stream_{m}_mse"] > 0 for r in ad["tests"])
    # the three fitted memories flown as one bank, mixed by predictions made ten samples
    # ahead: scored on both streams, its update fixed in memory
    assert all(r["stream_bank_mse"] > 0 and 0 <= r["stream_bank_coverage95"] <= 1
               for r in ad["tests"])  # fmt: skip
    assert ad["bank_update"]["bytes_start"] == ad["bank_update"]["bytes_end"]
    # its weights' forgetting fitted on the training streams, with what its band held there
    cover = ad["bank_fit"]["coverage95"]
    assert len(cover) == 6 and all(0 < c <= 1 for c in cover)
    sweep = {s["model"]: s["held_out_log_likelihood"] for s in ad["spread_sweep"]}
    uniform = [f"tracked_spread_{s:g}" for s in cfg["track"]["spread_sweep"]]
    assert set(sweep) == {*uniform, "tracked", "tracked_one_spread"}
    assert sweep["tracked"] >= max(sweep.values()) - 1e-6
    for m in [*uniform, "tracked_one_spread"]:
        assert all(np.isfinite(r[f"{m}_lpd_labels"]) for r in ad["tests"])
    for r in ad["tests"]:  # the filters reading every sample, scored at the same labels
        assert r["stream_scored"] == r["labels"] < r["stream_labels"]
        assert all(r[f"stream_{m}_mse"] > 0 for m in ("inducing", "tracked", "tracked_gusts",
                                                      "tracked_fit_stream",
                                                      "tracked_gusts_fit_stream"))  # fmt: skip
        # the offline model reads nothing: the same predictions at the same labels
        assert r["stream_none_mse"] == pytest.approx(r["none_mse"], rel=1e-9)
        # each term fitted on the whole stream in hindsight, scored at the same labels; the
        # inducing-point term reading it with each other forgetting time
        assert all(r[f"stream_hindsight_{m}_mse"] > 0 for m in ("tracked", "inducing"))
        assert all(r[f"stream_inducing_tau_{v:g}_mse"] > 0 for v in cfg["adapt"]["stream_taus"])
    # today's adaptation (on the correction before the physical basis), each forgetting
    # time, reading the labels and every sample at the same instants; the best is one of them
    today = ad["today"]
    assert today["taus"] == cfg["adapt"]["today_taus"]
    for r, t in zip(ad["tests"], today["tests"], strict=True):
        assert t["test"] == r["test"] and t["stream_scored"] == r["labels"]
        for reading in ("labels", "stream"):
            mses = [t[f"{reading}_tau_{v:g}_mse"] for v in today["taus"]]
            assert t[f"{reading}_best_mse"] == min(mses) > 0
            assert t[f"{reading}_tau_{t[f'{reading}_best_tau']:g}_mse"] == min(mses)
    assert (tmp_path / "figures" / "prequential_along_flight.png").is_file()
