"""The fit benchmark's quick version (CI): runs on a shipped recording, no MuJoCo needed."""

import importlib.util
import json
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "fit" / "benchmark.py"


def test_quick_fit_benchmark_writes_its_table(tmp_path):
    spec = importlib.util.spec_from_file_location("fit_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    summary = module.main(["--quick", "--out", str(tmp_path), "--work", str(tmp_path / "work")])
    saved = json.loads((tmp_path / "quick.json").read_text())
    assert saved["n"] == 1 and 0.0 <= saved["success_rate"] <= 1.0
    row = saved["rows"][0]
    for key in ("rotation_error_deg", "position_error_pct_depth", "gravity_error_deg", "mean_iou_true_masks"):
        assert np.isfinite(row[key])
    assert 0.0 < row["mean_iou_true_masks"] <= 1.0
    assert summary["rows"][0]["recording"] == "tshape_small"
