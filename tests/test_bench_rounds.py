"""Quick run of experiments/discover/bench_rounds.py: a round of discover's refits on the shipped
T-handle, each fit alone, one candidate's at a time and all side by side, ending in one place."""

import importlib.util
import json
import math
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "discover" / "bench_rounds.py"


def test_quick_round_writes_json_and_the_ways_agree(tmp_path):
    spec = importlib.util.spec_from_file_location("bench_rounds", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_rounds"] = module
    spec.loader.exec_module(module)
    out = tmp_path / "quick.json"
    returned = module.main(["--quick", "--repeats", "1", "--out", str(out)])
    data = json.loads(out.read_text())
    assert data == json.loads(json.dumps(returned))
    round_ = data["round"]
    assert round_["fits"] == 2 * 3  # two candidates, each on all frames and on two splits' train frames
    for key in ("each_fit_alone_s", "one_candidate_at_a_time_s", "side_by_side_s", "speedup"):
        assert math.isfinite(round_[key]) and round_[key] > 0
    for key in ("largest_difference", "largest_difference_one_candidate_at_a_time"):
        # the same fits whichever way they run: chi-squared to 1e-6, parameters to 1e-6 relative
        assert data[key]["chi2"] < 1e-6 and data[key]["params_relative"] < 1e-6
        assert data[key]["heldout_rms"] < 1e-6
