"""The paper's optimiser (torchfit.paper.method) and the convergence-basin experiment."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.camera import Camera
from torchfit.dynamics import RigidBody
from torchfit.paper import basin
from torchfit.paper.method import (
    PaperSettings,
    hard_loss,
    hybrid_gradient,
    paper_fit,
    parameter_scales,
    pose_jacobian,
)
from torchfit.render import RenderMesh
from torchfit.report import score_against_truth
from torchfit.rotation import (
    axis_angle_to_quat,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
)
from torchfit.search import Problem
from torchfit.shape import load_shape

SMALL = Path(__file__).resolve().parents[1] / "torchfit" / "recordings" / "tshape_small"


def _problem(dtype=torch.float32) -> tuple[Problem, dict]:
    """tshape_small from its true masks (no segmentation): 12 frames of 320x240."""
    truth = json.loads((SMALL / "truth.json").read_text())
    shape = load_shape(str(SMALL / "mesh.obj"), density=float(truth["object"]["density"]))
    camera = Camera.from_file(SMALL / "camera.json")
    masks = torch.as_tensor(np.load(SMALL / "masks.npz")["masks"], dtype=dtype)
    boxes = []
    for mask in masks:
        rows, cols = torch.nonzero(mask > 0.5, as_tuple=True)
        boxes.append([float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max())])
    times = torch.arange(len(masks), dtype=dtype) / float(truth["fps"])
    problem = Problem(shape, camera, RenderMesh.from_shape(shape, dtype), RigidBody.from_shape(shape, dtype), times,
                      masks, torch.tensor(boxes, dtype=dtype), torch.ones(len(masks), dtype=torch.bool),
                      g=float(truth["g"]))
    return problem, truth


def _truth_state(truth: dict, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    params = truth["params"]
    state = torch.tensor(params["position"] + params["orientation_wxyz"] + params["velocity"]
                         + params["angular_velocity"], dtype=dtype)
    return state, torch.tensor(truth["gravity_dir"], dtype=dtype)


def _params(problem: Problem, state: torch.Tensor, direction: torch.Tensor):
    """(base, params) of a state as paper_fit sets them up (zero iterations)."""
    result = paper_fit(problem, state, direction, PaperSettings(iterations=0))
    cands = result.candidates
    return cands.base[0], torch.cat([getattr(cands, name)[0] for name in cands.fields()[1:]])


def _turned(state: torch.Tensor, degrees: float, axis=(0.3, -0.5, 0.8)) -> torch.Tensor:
    axis = torch.tensor(axis, dtype=state.dtype)
    out = state.clone()
    out[3:7] = quat_multiply(axis_angle_to_quat(axis / axis.norm() * math.radians(degrees)), state[3:7])
    return out


def test_pose_jacobian_matches_finite_differences_float64():
    problem, truth = _problem(torch.float64)
    state, direction = _truth_state(truth, torch.float64)
    base, params = _params(problem, state, direction)
    _, rot, jacobian = pose_jacobian(problem, base, params)
    assert jacobian.shape == (len(problem.times), 6, 14)
    step = 1e-6
    for column in range(14):
        shift = torch.zeros(14, dtype=torch.float64)
        shift[column] = step
        plus, rot_plus, _ = pose_jacobian(problem, base, params + shift)
        minus, rot_minus, _ = pose_jacobian(problem, base, params - shift)
        d_com = (plus - minus) / (2 * step)
        # world-frame rotation vector of R(p ± h) Rᵀ(p), from the quaternion's vector part
        rel_plus = matrix_to_quat(rot_plus @ rot.transpose(-1, -2))
        rel_minus = matrix_to_quat(rot_minus @ rot.transpose(-1, -2))
        d_rot = (2 * rel_plus[:, 1:] - 2 * rel_minus[:, 1:]) / (2 * step)
        torch.testing.assert_close(jacobian[:, :3, column], d_com, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(jacobian[:, 3:, column], d_rot, rtol=1e-5, atol=1e-6)


def test_hybrid_gradient_points_like_finite_differences_of_the_hard_loss():
    """Hard silhouettes are piecewise constant, so only the direction can be compared: with steps
    that move edges by pixels, the hybrid gradient and a central-difference gradient of the hard
    loss w.r.t. the 14 parameters agree in direction, and a step against it lowers the loss."""
    problem, truth = _problem(torch.float64)
    state, direction = _truth_state(truth, torch.float64)
    guess = _turned(state, 6.0)
    guess[0:3] += torch.tensor([0.01, -0.005, 0.02], dtype=torch.float64)
    base, params = _params(problem, guess, direction)
    settings = PaperSettings(crop=64)
    scales = parameter_scales(problem)
    loss, gradient = hybrid_gradient(problem, base, params, settings, scales)
    assert gradient.shape == (14,)
    torch.testing.assert_close(loss, hard_loss(problem, base[None], params[None], 64)[0])
    step = 0.02  # scaled units
    shifts = torch.diag(scales) * step
    plus = hard_loss(problem, base.expand(14, 4), params + shifts, 64)
    minus = hard_loss(problem, base.expand(14, 4), params - shifts, 64)
    numeric = (plus - minus) / (2 * step)
    cosine = float(gradient @ numeric / (gradient.norm() * numeric.norm()))
    assert cosine > 0.95, f"hybrid vs finite-difference gradient: cosine {cosine:.3f}"
    descended = hard_loss(problem, base[None], (params - 0.05 * scales * gradient / gradient.norm())[None], 64)
    assert float(descended[0]) < float(loss)


def test_paper_fit_from_the_truth_stays_there():
    problem, truth = _problem()
    state, direction = _truth_state(truth, torch.float32)
    result = paper_fit(problem, state, direction, PaperSettings(iterations=5))
    assert result.loss <= result.loss_curve[0] < 0.02
    assert result.state.shape == (13,) and result.gravity.shape == (3,)
    rot = quat_to_matrix(result.state[3:7])
    true_rot = quat_to_matrix(state[3:7])
    assert math.degrees(float(torch.acos(((rot * true_rot).sum() - 1).clamp(-2, 2) / 2))) < 1.0


def test_paper_fit_descends_from_a_small_perturbation():
    problem, truth = _problem()
    state, direction = _truth_state(truth, torch.float32)
    result = paper_fit(problem, _turned(state, 5.0), direction, PaperSettings(iterations=12))
    assert result.loss < 0.8 * result.loss_curve[0]
    assert all(b <= a for a, b in zip(result.loss_curve, result.loss_curve[1:]))  # descent only
    span = np.arange(len(problem.times))
    score = score_against_truth(str(SMALL / "truth.json"), result.as_fit_result(), problem, problem.shape, span)
    assert score["rotation_error_deg"] < 5.0


@pytest.mark.parametrize("bad", [{"fd_steps": (0.01, 0.01)}, {"fd_steps": (0, 1, 1, 1, 1, 1)}, {"crop": 4},
                                 {"step": 0.0}, {"iterations": -1}])
def test_bad_settings_fail(bad):
    with pytest.raises(ValueError, match="fd_steps|crop|step|iterations"):
        PaperSettings(**bad)


def test_bad_guess_fails():
    problem, truth = _problem()
    state, direction = _truth_state(truth, torch.float32)
    with pytest.raises(ValueError, match="initial_state"):
        paper_fit(problem, state[:7], direction)
    with pytest.raises(ValueError, match="gravity_dir"):
        paper_fit(problem, state, torch.zeros(3))


def test_quick_basin_runs(tmp_path):
    summary = basin.main(tmp_path, quick=True, progress=None)
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
    assert (tmp_path / "basin.png").stat().st_size > 0
    assert [row["level_deg"] for row in summary["levels"]] == [0.0, 15.0]
    assert summary["levels"][0]["successes"] == 1  # from the truth the paper's method stays put
    assert summary["torchfit"]["trials"] == 1 and set(summary["target"]) == {
        "success_at_least_paper_15deg", "faster_than_paper_15deg", "less_cpu_than_paper_15deg", "holds"}
