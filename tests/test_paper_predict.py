"""Paper Figs. 4-5 (torchfit.paper.predict): residuals, their autograd Jacobian, the Laplace draws, the quick run."""

import itertools
import json
import math

import numpy as np
import pytest
import torch

from torchfit.camera import tilt_roll_from_direction
from torchfit.paper._recording import load_recording
from torchfit.paper.predict import (
    N_PARAMS,
    laplace_samples,
    levenberg_marquardt,
    main,
    perturb,
    residual_jacobian,
    silhouette_residuals,
    step_size,
)
from torchfit.rotation import matrix_to_quat
from torchfit.search import Candidates, candidate_losses


def _small_problem(frames=6):
    from torchfit.run import build_problem
    from torchfit.video import load_observation

    rec = load_recording("tshape_small")
    observation = load_observation(str(rec.video), camera=rec.camera, stop=frames)
    problem, _ = build_problem(observation, rec.shape, rec.camera, g=9.81, dtype=torch.float64, device="cpu")
    truth = rec.truth["params"]
    rot = torch.tensor(truth["R"], dtype=torch.float64)
    com = rot @ torch.as_tensor(rec.shape.com) + torch.tensor(truth["position"], dtype=torch.float64)
    omega = torch.tensor(truth["angular_velocity"], dtype=torch.float64)
    velocity = torch.tensor(truth["velocity"], dtype=torch.float64) + torch.cross(
        omega, rot @ torch.as_tensor(rec.shape.com), dim=-1)
    tilt, roll = tilt_roll_from_direction(torch.tensor(rec.truth["gravity_dir"], dtype=torch.float64))
    # a little off the truth, so the residuals are not zero
    cands = Candidates(matrix_to_quat(rot)[None], torch.tensor([[0.02, -0.01, 0.03]], dtype=torch.float64),
                       com[None] + 0.002, velocity[None], omega[None] + 0.1,
                       torch.stack((tilt, roll))[None].double())
    return problem, cands


def test_residuals_square_to_the_search_loss():
    problem, cands = _small_problem()
    frames = len(problem.times)
    res = silhouette_residuals(problem, cands, crop=24, sigma=1.0, step=step_size(problem, cands, frames))
    assert res.shape == (1, frames * (24 * 24 + 2))
    loss = candidate_losses(problem, cands, frames, 24, 1.0)
    assert float(res.square().sum()) == pytest.approx(float(loss[0]), rel=1e-10)


def test_jacobian_of_a_known_function():
    def residuals(p):
        return torch.stack((p[0] ** 2, torch.sin(p[1]), p[0] * p[1], 3 * p[2]))

    point = torch.tensor([0.7, -0.3, 2.0], dtype=torch.float64)
    res, jac = residual_jacobian(residuals, point)
    x, y, _ = point.tolist()
    expected = torch.tensor([[2 * x, 0, 0], [0, math.cos(y), 0], [y, x, 0], [0, 0, 3]], dtype=torch.float64)
    assert torch.allclose(res, residuals(point))
    assert torch.allclose(jac, expected, atol=1e-12)


def test_jacobian_through_simulation_and_renderer_matches_finite_differences():
    """float64: the double-vjp Jacobian of the silhouette residuals vs central differences."""
    problem, cands = _small_problem(frames=6)
    step = step_size(problem, cands, len(problem.times))

    def residuals(p):
        return silhouette_residuals(problem, perturb(cands, p[None]), crop=16, sigma=1.5, step=step)[0]

    point = torch.zeros(N_PARAMS, dtype=torch.float64)
    _, jac = residual_jacobian(residuals, point)
    eps = 1e-6
    numeric = torch.stack([(residuals(point + eps * e) - residuals(point - eps * e)) / (2 * eps)
                           for e in torch.eye(N_PARAMS, dtype=torch.float64)], -1)
    assert jac.shape == numeric.shape == (6 * (16 * 16 + 2), N_PARAMS)
    for i in range(N_PARAMS):  # each column: orientation, position, velocity, spin, gravity
        scale = float(numeric[:, i].norm())
        assert scale > 0
        assert float((jac[:, i] - numeric[:, i]).norm()) < 1e-5 * scale, i


def test_levenberg_marquardt_finds_the_rosenbrock_minimum():
    def residuals(p):
        return torch.stack((10 * (p[1] - p[0] ** 2), 1 - p[0]))

    point, losses = levenberg_marquardt(residuals, torch.tensor([-1.2, 1.0], dtype=torch.float64), 100)
    assert torch.allclose(point, torch.tensor([1.0, 1.0], dtype=torch.float64), atol=1e-6)
    assert all(b <= a for a, b in itertools.pairwise(losses)) and losses[-1] < 1e-12


def test_laplace_draws_have_the_least_squares_covariance():
    generator = torch.Generator().manual_seed(0)
    jac = torch.randn(200, 3, dtype=torch.float64, generator=generator)
    jac[:, 2] = 0.0  # a direction the data do not constrain
    res = 0.1 * torch.randn(200, dtype=torch.float64, generator=generator)
    draws, cov = laplace_samples(jac, res, 20000, inflation=2.0, generator=generator)
    noise = float(res.square().sum()) / (200 - 3)
    expected = 4.0 * noise * torch.linalg.inv(jac[:, :2].T @ jac[:, :2])
    assert torch.allclose(cov[:2, :2], expected, rtol=1e-9)
    assert torch.allclose(torch.cov(draws[:, :2].T), expected, rtol=0, atol=0.05 * float(expected.diagonal().max()))
    assert float(draws[:, 2].abs().max()) == 0.0 and float(cov[2].abs().max()) == 0.0


def test_perturb_checks_its_input_and_zero_is_the_candidate():
    problem, cands = _small_problem()
    same = perturb(cands, torch.zeros(2, N_PARAMS, dtype=torch.float64))
    assert torch.allclose(same.state(problem.body), cands.state(problem.body).expand(2, 13), atol=1e-12)
    with pytest.raises(ValueError, match=r"offsets must have shape \(M, 14\)"):
        perturb(cands, torch.zeros(2, 13, dtype=torch.float64))


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="window must be at least 6"):
        main("unused", window=3, progress=None)
    with pytest.raises(ValueError, match="samples must be >= 1"):
        main("unused", samples=0, progress=None)


def test_quick_run_writes_figures_and_summary(tmp_path):
    summary = main(tmp_path, quick=True, progress=None)
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
    for name in summary["figures"].values():
        assert (tmp_path / name).stat().st_size > 10_000
    row = summary["recordings"]["tshape_small"]
    assert row["frames_fitted"] == [0, 6] and row["frames_total"] == 12
    assert row["iou_fitted_mean"] > 0.6
    assert row["rotation_error_fitted_max_deg"] < 15
    low, mid, high = row["band_last_frame"]["rotation_error_deg"]
    assert np.isfinite([low, mid, high]).all() and low <= mid <= high
    assert all(np.isfinite(v) and v > 0 for v in row["laplace_std"].values())
    # Levenberg-Marquardt lowers the loss and ends where the Gauss-Newton step is tiny
    assert row["lm_losses"][-1] < row["lm_losses"][0]
    assert row["newton_step_at_fit"]["rotation_deg"] < 0.1
    assert row["horizon"]["integrator_vs_mujoco_deg"] < 0.1


def test_frame_sandwich_matches_laplace_for_independent_residuals_and_widens_for_correlated_ones():
    """With independent residuals the per-frame sandwich agrees with s²(JᵀJ)⁻¹; when each frame's
    residuals share one error (an edge displaced as a whole), it is much wider, as it should be."""
    generator = torch.Generator().manual_seed(1)
    frames, rows = 400, 25
    jac = torch.randn(frames * rows, 2, dtype=torch.float64, generator=generator)
    jac[:, 1] = 1.0 + 0.1 * jac[:, 1]  # a parameter every pixel of a frame responds to alike
    independent = 0.1 * torch.randn(frames * rows, dtype=torch.float64, generator=generator)
    shared = 0.1 * torch.randn(frames, 1, dtype=torch.float64, generator=generator).expand(frames, rows).reshape(-1)
    for res, ratio in ((independent, (0.8, 1.25)), (shared, (3.0, 7.0))):
        res = res - jac @ torch.linalg.lstsq(jac, res[:, None]).solution[:, 0]  # at the optimum
        _, plain = laplace_samples(jac, res, 1)
        draws, sandwich = laplace_samples(jac, res, 4000, clusters=frames, generator=generator)
        wider = float((sandwich[1, 1] / plain[1, 1]).sqrt())
        assert ratio[0] < wider < ratio[1], wider
    assert torch.allclose(torch.cov(draws.T), sandwich, rtol=0.1, atol=0.1 * float(sandwich.diagonal().max()))
    with pytest.raises(ValueError, match="clusters must be"):
        laplace_samples(jac, res, 1, clusters=7)
