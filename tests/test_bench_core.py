"""Smoke test of experiments/bench_core.py: the --quick run writes JSON with the expected keys."""

import importlib.util
import json
import math
from pathlib import Path

import pytest

from torchfit import render

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "bench_core.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_core", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _positive(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def test_quick_run_writes_expected_json(bench, tmp_path):
    out = tmp_path / "quick.json"
    try:
        returned = bench.main(["--quick", "--no-compile", "--device", "cpu", "--out", str(out)])
    finally:
        render.set_compile(False)
    data = json.loads(out.read_text())
    assert data == json.loads(json.dumps(returned))
    assert set(data) >= {"env", "config", "render", "integrator", "ball"}

    env = data["env"]
    for key in ("torch", "device", "threads", "cpu_model", "date"):
        assert key in env
    assert env["device"] == "cpu" and env["threads"] >= 1

    cases = data["render"]["cases"]
    assert [(c["mode"], c["size"], c["n"]) for c in cases] == [("eager", 32, 256)]
    for key in ("fwd_bwd_per_s", "fwd_bwd_median_s", "fwd_per_s", "fwd_median_s"):
        assert _positive(cases[0][key]), key
    assert cases[0]["grads_finite"] is True
    assert data["render"]["ratios"] == []  # no compiled run to compare

    integ = data["integrator"]
    assert integ["frames"] == 40 and integ["fps"] == 30 and integ["method"] == "rk4"
    for key in ("forward_s", "fwd_bwd_s"):
        assert _positive(integ[key]), key
    assert integ["grads_finite"] is True

    ball = data["ball"]
    for name in ("sphere", "mesh"):
        for key in ("moments_median_s", "coverage_fwd_bwd_median_s"):
            assert _positive(ball[name][key]), (name, key)
        assert ball[name]["grads_finite"] is True
    # the sphere is the true silhouette to rounding; the mesh's facets are not
    assert ball["sphere"]["area_error_max"] < 1e-9 and ball["sphere"]["centroid_error_max_px"] < 1e-9
    assert ball["mesh"]["area_error_max"] > 1e-4
    assert _positive(ball["moments_mesh_over_sphere"]) and _positive(ball["coverage_mesh_over_sphere"])


def test_poses_are_in_view_and_windows_cover_them(bench):
    import torch

    from torchfit.shape import load_shape

    mesh = render.RenderMesh.from_shape(load_shape(primitive="tshape", density=600.0))
    rot, trans, windows = bench.make_poses(64, (32, 32), mesh, torch.Generator().manual_seed(0), "cpu")
    assert rot.shape == (4, 16, 3, 3) and trans.shape == (4, 16, 3) and windows.shape == (4, 16, 3)
    eye = torch.eye(3).expand(4, 16, 3, 3)
    assert torch.allclose(rot @ rot.transpose(-1, -2), eye, atol=1e-5)
    hard = render.render_silhouettes(mesh, bench.CAMERA, rot, trans, windows, size=(32, 32), sigma=None)
    area = hard.mean(dim=(-1, -2))
    # the silhouette is inside the crop (margin: border pixels empty) and not vanishingly small
    assert bool((area > 0.02).all())
    border = torch.cat((hard[..., 0, :], hard[..., -1, :], hard[..., :, 0], hard[..., :, -1]), dim=-1)
    assert float(border.max()) == 0.0


def test_sections_measure_only_what_is_asked(bench, tmp_path):
    out = tmp_path / "ball.json"
    data = bench.main(["--quick", "--no-compile", "--device", "cpu", "--sections", "ball", "--out", str(out)])
    assert set(data) == {"env", "config", "ball"} and data["config"]["sections"] == ["ball"]
    assert "mesh / sphere" in bench.format_table(data)
