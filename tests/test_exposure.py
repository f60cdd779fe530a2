"""Motion blur in the model: poses over the exposure, the exposure's average moments, and the
soft coverage they are compared with."""

import math

import numpy as np
import pytest
import torch

from torchfit.camera import Camera
from torchfit.dynamics import RigidBody, simulate
from torchfit.losses import central_moments, raw_from_central
from torchfit.render import RenderMesh, full_window, render_silhouettes, silhouette_moments
from torchfit.residuals import channel_values
from torchfit.rotation import axis_angle_to_quat, rotation_angle
from torchfit.search import Candidates, Exposure, Problem, candidate_moments, candidate_poses, exposure_poses
from torchfit.shape import load_shape
from torchfit.video import _boxes, raw_moments

F64 = torch.float64
FPS = 60.0


def _throw(frames=16, com_offset=(0.0, 0.0, 0.0)):
    """A spinning box thrown past a small camera (its centre of mass moved by ``com_offset``, m,
    mesh frame), as a float64 problem with empty masks, and its true candidate."""
    shape = load_shape(primitive="box", dims={"extents": [0.16, 0.08, 0.04]}, density=300.0)
    body = RigidBody.from_shape(shape, F64)
    body = RigidBody(body.mass, body.com + torch.tensor(com_offset, dtype=F64), body.inertia)
    camera = Camera(300.0, 300.0, 79.5, 59.5, 160, 120)
    times = torch.arange(frames, dtype=F64) / FPS
    quat = axis_angle_to_quat(torch.tensor([[0.3, 0.5, -0.2]], dtype=F64))
    com, vel, omega = (torch.tensor([x], dtype=F64) for x in ([-0.25, 0.05, 2.0], [1.2, -2.0, 0.2], [1.0, 12.0, 2.0]))
    cands = Candidates(quat, torch.zeros(1, 3, dtype=F64), com, vel, omega, torch.tensor([[0.05, -0.1]], dtype=F64))
    problem = Problem(shape, camera, RenderMesh.from_shape(shape, F64), body, times,
                      torch.zeros(frames, 120, 160, dtype=F64), torch.zeros(frames, 4, dtype=F64),
                      torch.ones(frames, dtype=torch.bool))
    return problem, cands


def _flight_at(problem, cands, offset):
    """(T - 1, 3, 3) rotations and (T - 1, 3) positions of the simulated flight ``offset`` seconds
    after frames 1..T-1 (the state is the one at t = 0)."""
    times = torch.cat((torch.zeros(1, dtype=F64), problem.times[1:] + offset))
    traj = simulate(cands.state(problem.body), times, problem.body, cands.gravity(problem.g), [])
    return traj.rot[0, 1:], traj.position[0, 1:]


@pytest.mark.parametrize("com_offset", [(0.0, 0.0, 0.0), (0.03, -0.01, 0.005)])
def test_poses_over_the_exposure_follow_the_simulated_flight(com_offset):
    """A quarter frame either side (4.2 ms at 60 fps) the free-flight step lands where the ODE
    does: the centre of mass exactly on its parabola, the turn within 2e-4 rad (the spin's change,
    left out, is second order); the frame's own pose is 0.05 rad away, so the step is no no-op."""
    problem, cands = _throw(com_offset=com_offset)
    rot, position, motion = (x[:, 1:] for x in candidate_poses(problem, cands, len(problem.times)))
    for offset in (-0.25 / FPS, 0.25 / FPS):
        moved_rot, moved_position, _ = exposure_poses(rot, position, motion, problem.body.com,
                                                      cands.gravity(problem.g), torch.tensor(offset, dtype=F64))
        true_rot, true_position = _flight_at(problem, cands, offset)
        assert float(rotation_angle(moved_rot[0], true_rot).max()) < 2e-4
        assert float(rotation_angle(rot[0], true_rot).min()) > 0.04
        assert float((moved_position[0] - true_position).norm(dim=-1).max()) < 2e-5  # m, a lever of ~9 cm turned


@pytest.mark.parametrize("taps, samples", [(5, 5), (0, 81)])
def test_exposure_average_is_the_average_of_the_silhouette_over_the_shutter(taps, samples):
    """The three-point rule against the raw moments averaged over the exact flight: the 5 equal
    sub-frames of a generated recording, or a camera's continuous exposure (81-point trapezoid),
    for a box turning 0.05 rad and moving ~9 px over half a frame. In the residual channels the
    rule's error is under a tenth of what the blur changes in the centroid and the orientation;
    in size and elongation it is under 0.003 and 0.006 (measured 0.0026 and 0.0057 in the frame
    where a face turns edge-on, whose area has a kink in time: the rule is exact only for
    smooth moments), against noise floors of 0.005-0.03 on the concealed recordings."""
    problem, cands = _throw()
    frames = len(problem.times)
    half = 0.25 / FPS
    offsets = torch.linspace(-half, half, samples, dtype=F64)
    weights = torch.ones(samples, dtype=F64)
    if taps == 0:
        weights[0] = weights[-1] = 0.5
    weights = weights / weights.sum()
    raws = [raw_from_central(*silhouette_moments(problem.mesh, problem.camera, *_flight_at(problem, cands, float(o))))
            for o in offsets]
    truth = central_moments(sum(w * r for w, r in zip(weights, raws)))
    averaged = [m[0, 1:] for m in candidate_moments(problem, cands, frames, exposure=Exposure(0.5, taps))]
    instant = [m[0, 1:] for m in candidate_moments(problem, cands, frames)]
    error, blur = channel_values(truth, averaged), channel_values(truth, instant)
    for channel in ("centroid_x", "centroid_y", "orientation"):
        assert float(error[channel].abs().max()) < 0.1 * float(blur[channel].abs().max()), channel
    assert float(error["scale"].abs().max()) < 0.003 < float(blur["scale"].abs().max())
    assert float(error["shape"].abs().max()) < 0.006 < float(blur["shape"].abs().max())
    assert Exposure(0.0).end_weight == pytest.approx(1 / 6) and Exposure(0.5, 5).end_weight == pytest.approx(0.25)
    for bad in ({"fraction": 1.5}, {"fraction": float("nan")}, {"fraction": 0.5, "taps": 1}):
        with pytest.raises(ValueError, match="exposure"):
            Exposure(**bad)


def _blurred_throw():
    """:func:`_throw` drawn as a generated recording is: its (T, 120, 160) coverage averaged over
    5 sub-frames over half the frame interval, each sampled at pixel centres; the problem's masks
    and boxes are the coverage's 0.5 contour. Returns the problem, the true candidate and the coverage."""
    problem, cands = _throw()
    frames = len(problem.times)
    rot, position, motion = candidate_poses(problem, cands, frames)
    half = torch.tensor(0.25 / FPS, dtype=F64)
    cover = torch.zeros(frames, 120, 160, dtype=F64)
    for offset in torch.linspace(-1.0, 1.0, 5, dtype=F64) * half:
        r, p, _ = exposure_poses(rot, position, motion, problem.body.com, cands.gravity(problem.g), offset)
        cover += render_silhouettes(problem.mesh, problem.camera, r, p, full_window(problem.camera, 1, frames, dtype=F64),
                                    size=(120, 160), sigma=None)[0] / 5
    masks = cover >= 0.5
    problem.masks = masks.to(F64)
    problem.boxes = torch.as_tensor(np.nan_to_num(_boxes(masks.numpy())), dtype=F64)
    return problem, cands, cover


def test_coverage_against_the_exposure_fits_a_blurred_throw_that_masks_do_not():
    """A thrown box drawn as a generated recording is (coverage averaged over 5 sub-frames over
    half the frame interval, each sampled at pixel centres): at the true model the soft coverage
    against the exposure's average is nearer in every channel than the 0.5 contour (the mask)
    against the frame's instant (measured RMS, coverage against mask: centroid 0.016 / 0.041 px,
    scale 0.0012 / 0.0042, shape 0.0038 / 0.0053, orientation 0.0019 / 0.0055; what is left is
    the pixel sampling of a silhouette of 90-290 px²). VideoProblem refuses an exposure
    without coverage."""
    import torchfit.discover_video as dv
    from torchfit.discover_video import _Model

    problem, cands, cover = _blurred_throw()
    exposure = Exposure(0.5, 5)
    base = _Model(cands, {})
    rms = {}
    for label, kwargs in (("mask", {}), ("coverage", {"exposure": exposure,
                                                       "coverage": torch.as_tensor(raw_moments(cover.numpy()))})):
        video = dv.VideoProblem(problem, candidates=(), **kwargs)
        video._set_noise(base)
        channels = video.residuals(base)
        rms[label] = {c: float(np.sqrt(np.nanmean(v**2))) for c, v in channels.items()}
    assert max(rms["coverage"]["centroid_x"], rms["coverage"]["centroid_y"]) < 0.02, rms
    assert rms["coverage"]["scale"] < 0.002, rms
    assert all(rms["coverage"][c] < rms["mask"][c] for c in rms["mask"]), rms
    with pytest.raises(ValueError, match="an exposure needs the"):
        dv.VideoProblem(problem, candidates=(), exposure=exposure)


def test_fitted_exposure_finds_the_shutter_the_blur_was_drawn_with():
    """``VideoProblem(fit_exposure=True)``: the exposure's fraction is a nuisance every model fits.
    On the blurred throw drawn over half the frame interval, started at a quarter, the refit from
    the true flight finds the fraction the coverage was drawn with (measured 0.484; its standard
    error, 0.15, is against noise floors taken at the start, where the quarter leaves the shape
    channel far off), while the given exposure alone (not fitted) leaves the shape channel
    further off. A fraction outside [0, 1] is refused as a step out of its domain."""
    import torchfit.discover_video as dv
    from torchfit.discover_video import _Model

    problem, cands, cover = _blurred_throw()
    coverage = torch.as_tensor(raw_moments(cover.numpy()))
    video = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.25, 5), coverage=coverage, fit_exposure=True)
    start = _Model(cands, {}, video.start_nuisances())
    assert start.nuisances == (0.0, 0.0, 0.25)
    video._set_noise(start)
    everything = video.problem.used.cpu().numpy().astype(bool)
    model, resid, jac = video._lm(start, everything, 15)
    fraction, std = model.nuisances[2], video._uncertainty(model, resid, jac)[1][2]
    assert abs(fraction - 0.5) < 0.03 and 0 < std < 0.25, (fraction, std)
    fixed = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.25, 5), coverage=coverage)
    fixed._set_noise(_Model(cands, {}))
    shape_fitted = float(np.sqrt(np.nanmean(video.residuals(model)["shape"] ** 2)))
    shape_fixed = float(np.sqrt(np.nanmean(fixed.residuals(_Model(cands, {}))["shape"] ** 2)))
    assert shape_fitted < 0.5 * shape_fixed, (shape_fitted, shape_fixed)
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        video._build(model, torch.zeros(1, 14, dtype=F64), torch.tensor([0.0, 0.0, 20.0], dtype=F64))
    with pytest.raises(ValueError, match="fit_exposure needs"):
        dv.VideoProblem(problem, candidates=(), fit_exposure=True)


def test_fitted_point_spread_and_exposure_find_what_the_coverage_was_drawn_with():
    """``VideoProblem(point_spread=(0, inf))``: an isotropic variance added to every silhouette's
    covariance is a nuisance every model fits. The blurred throw's coverage seen through a point
    spread of 1.5 px² (its raw moments' m20 and m02 raised by 1.5 m00: area and centre kept) and
    drawn over half the frame interval: started at no spread and a quarter, the refit from the true
    flight finds both (measured 1.58 ± 0.34 px² and 0.490 ± 0.113 on every frame; the errors are
    against noise floors taken at the start, far off), and the nuisances keep their order (edge bias,
    point spread, exposure). A point spread without the coverage is refused."""
    import torchfit.discover_video as dv
    from torchfit.discover_video import _Model

    problem, cands, cover = _blurred_throw()
    coverage = torch.as_tensor(raw_moments(cover.numpy()))
    coverage[:, 3] += 1.5 * coverage[:, 0]
    coverage[:, 5] += 1.5 * coverage[:, 0]
    # the jump test off: exact renders have no failed frame (on this coverage it takes frames 5-6,
    # and with their neighbours 4-7, which leaves the spread 1.61 ± 0.67, this test not about it)
    video = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.25, 5), coverage=coverage,
                            fit_exposure=True, point_spread=(0.0, math.inf), jump_sigmas=None)
    assert video.nuisance_names == ("edge", "edge_shape", "point_spread", "exposure")
    start = _Model(cands, {}, video.start_nuisances())
    assert start.nuisances == (0.0, 0.0, 0.0, 0.25)
    video._set_noise(start)
    everything = video.problem.used.cpu().numpy().astype(bool)
    model, resid, jac = video._lm(start, everything, 15)
    std = video._uncertainty(model, resid, jac)[1]
    spread, fraction = video.nuisance(model.nuisances, "point_spread"), video.nuisance(model.nuisances, "exposure")
    assert abs(spread - 1.5) < 0.1 and 0 < std[2] < 1.0, (spread, fraction, std)
    assert abs(fraction - 0.5) < 0.03 and 0 < std[3] < 0.3, (spread, fraction, std)
    with pytest.raises(ValueError, match="point_spread needs"):
        dv.VideoProblem(problem, candidates=(), point_spread=(0.0, math.inf))


def test_point_spread_prior_holds_the_spread_and_counts_as_an_observation():
    """``VideoProblem(point_spread=(mean, std))``: the spread starts at ``mean`` and its prior term
    ``(s - mean) / std`` joins the edge bias's two among the residuals (and the criterion's
    observations); without a prior (``std`` infinite) there is no term. The throw's coverage drawn
    through 1.5 px²: a loose prior (1 ± 1 px²) still finds it (measured 1.52), a tight one at 0
    (± 0.05 px²) holds the spread near 0 (measured 0.06). A bad prior is refused with its value."""
    import torchfit.discover_video as dv
    from torchfit.discover_video import EDGE_PRIOR_PX, EDGE_SHAPE_PRIOR_PX, _Model

    problem, cands, cover = _blurred_throw()
    coverage = torch.as_tensor(raw_moments(cover.numpy()))
    coverage[:, 3] += 1.5 * coverage[:, 0]
    coverage[:, 5] += 1.5 * coverage[:, 0]
    everything = problem.used.cpu().numpy().astype(bool)
    found = {}
    for prior in ((1.0, 1.0), (0.0, 0.05)):
        video = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.5, 5), coverage=coverage,
                                point_spread=prior)
        start = _Model(cands, {}, video.start_nuisances())
        assert start.nuisances == (0.0, 0.0, prior[0])
        assert video.prior_terms((0.03, -0.06, 2.0)) == pytest.approx(
            (0.03 / EDGE_PRIOR_PX, -0.06 / EDGE_SHAPE_PRIOR_PX, (2.0 - prior[0]) / prior[1]))
        video._set_noise(start)
        model, resid, jac = video._lm(start, everything, 15)
        found[prior] = video.nuisance(model.nuisances, "point_spread")
        fit = video._score((), model, video._uncertainty(model, resid, jac), [model])
        assert fit.n_obs == int(np.isfinite(np.concatenate(list(video.whitened_channels(
            video.residuals(model), video.problem.used.cpu().numpy().astype(bool)).values()))).sum()) + 3
    assert abs(found[(1.0, 1.0)] - 1.5) < 0.2, found
    assert abs(found[(0.0, 0.05)]) < 0.2, found
    free = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.5, 5), coverage=coverage,
                           point_spread=(0.0, math.inf))
    assert len(free.prior_terms((0.0, 0.0, 2.0))) == 2
    with pytest.raises(ValueError, match="point_spread must be .*got \\(1.0, 0.0\\)"):
        dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.5, 5), coverage=coverage, point_spread=(1.0, 0.0))


def test_baseline_from_several_search_candidates_keeps_the_lowest_cost():
    """``VideoProblem(baseline_starts=K)``: the baseline's Levenberg-Marquardt runs from the
    search's first K candidates side by side and keeps the lowest cost. With the search's
    "best" a flight spun 5 rad/s off and its second the true one, two iterations from the first
    alone end at a cost of 72.5, from both at 1.44 (measured with the jump test off, 2026-12-01). A
    start count below 1 is refused with its value."""
    from types import SimpleNamespace

    import torchfit.discover_video as dv

    problem, cands, cover = _blurred_throw()
    coverage = torch.as_tensor(raw_moments(cover.numpy()))
    off = Candidates(*(getattr(cands, f).clone() for f in cands.fields()))
    off.omega[:, 0] += 5.0
    both = Candidates(*(torch.cat([getattr(off, f), getattr(cands, f)]) for f in cands.fields()))
    searched = SimpleNamespace(candidates=both)
    rss = {}
    for starts in (1, 2):
        # the jump test off: judged on the start spun off, it would leave out more frames than this
        # short clip can spare (MIN_FIT_FRAMES), and the starts are what is tested here
        video = dv.VideoProblem(problem, candidates=(), exposure=Exposure(0.5, 5), coverage=coverage,
                                iterations=2, baseline_starts=starts, jump_sigmas=None)
        rss[starts] = video.fit((), None, searched).rss
    assert rss[2] < 0.5 * rss[1], rss
    with pytest.raises(ValueError, match="baseline_starts must be .*got 0"):
        dv.VideoProblem(problem, candidates=(), baseline_starts=0)
