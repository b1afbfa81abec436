"""benchmarks.studies.image_probe: a tiny probe runs, writes results.json, and never overwrites one without --overwrite."""
import json

import pytest

from benchmarks.studies import image_probe


def test_probe_writes_results_and_refuses_to_overwrite(tmp_path, capsys):
    args = ["--encoders", "keypoints", "--samples", "64", "--epochs", "1", "--batch", "32", "--threads", "1",
            "--no-progress", "--out", str(tmp_path)]
    assert image_probe.main(args) == 0
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert rows[0]["encoder"] == "keypoints" and rows[0]["baseline_rmse_cm"] > 0
    with pytest.raises(SystemExit):
        image_probe.main(args)
    assert "pass --overwrite" in capsys.readouterr().err
    assert image_probe.main(args + ["--overwrite"]) == 0
