"""``experiments.export`` on smoke data, composed with Hydra: every format written, checked
against JAX and timed. A whole experiment (C compiles and drivers): the slow set; the
exports have fast tests in tests/export."""

import json

import pytest

from experiments.runs import export
from tests.helpers import compose_plain, finite_numbers

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("data", ["smoke", "envelope_smoke"])
def test_export_run(smoke_cache, tmp_path, data):
    """The airflow frame's smoke data and the body frame's (``data=envelope_smoke``: states in
    the ball, any attitude); the one-state ONNX graph beside the batched one."""
    overrides = [
        f"data={data}",
        "data.chunk=32",
        f"cache_dir={smoke_cache}",
        "checks.n_states=40",
        "checks.n_jacobians=5",
        "latency_calls=50",
        "c.calls=200",
    ]
    res = export.run(compose_plain("export", overrides), tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers(saved) and saved["record"]["model"] == "gpgs_hybrid"
    f = saved["formats"]
    for dtype, tol in (("double", 1e-10), ("float", 1e-4)):
        e = f["c"][dtype]["errors"]
        assert max(e["force"], e["torque"]) <= tol and e["in_domain_disagree"] == 0
        assert f["c"][dtype]["latency_us"]["predict"]["median_us"] > 0
        assert (tmp_path / "export" / f"gpg_model_{dtype}.c").is_file()
    assert f["casadi"]["errors"]["force"] <= 1e-10 and f["casadi"]["errors"]["jacobian"] <= 1e-8
    assert f["onnx"]["errors"]["force"] <= 1e-4
    assert f["onnx"]["one_state_graph"]["errors"]["force"] <= 1e-4
    assert f["onnx"]["one_state_graph"]["errors"]["in_domain_disagree"] == 0
    assert saved["record"]["gp_frame"] == ("body" if data == "envelope_smoke" else "airflow")
    assert (tmp_path / "export" / "gpg_model.onnx").is_file()
    assert (tmp_path / "export" / "gpg_model_one.onnx").is_file()
    assert "| C double |" in export.summary_table(res)


def test_export_refuses_an_unknown_format(tmp_path):
    with pytest.raises(ValueError, match="formats must be a non-empty list"):
        export.run(compose_plain("export", ["formats=[c,fortran]"]), tmp_path)
