"""``experiments.diff_results``: numbers compared exactly, timings left out."""

import json

from experiments.diff_results import main, numbers


def test_numbers_skip_timings_and_records(tmp_path):
    a = {
        "models": {
            "gpg": {
                "mae": [1.0, 2.0],
                "train_s": 5.0,
                "predict_ms_median": 3.0,
                "predict_ratio_to_gp": 0.5,
                "noise_ratio": 0.016,
            }
        },
        "machine": {"cores": 2},
    }
    got = numbers(a)
    assert got == {
        "models.gpg.mae[0]": 1.0,
        "models.gpg.mae[1]": 2.0,
        "models.gpg.noise_ratio": 0.016,
    }
    b = json.loads(json.dumps(a))
    b["models"]["gpg"]["train_s"] = 9.0  # a timing: not a difference
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "b.json").write_text(json.dumps(b))
    assert main([str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    b["models"]["gpg"]["mae"][1] = 2.0000001
    (tmp_path / "b.json").write_text(json.dumps(b))
    assert main([str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 1
    assert main([str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--rtol", "1e-6"]) == 0
