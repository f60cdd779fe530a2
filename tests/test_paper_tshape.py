"""Paper Fig. 3 (torchfit.paper.tshape_fig3): the flip construction, corners, the search hook, the quick run."""

import json
import math

import numpy as np
import pytest
import torch

from torchfit.dynamics import RigidBody, integrate
from torchfit.paper._recording import load_recording, search_settings
from torchfit.paper.tshape_fig3 import (
    corner_track,
    flip_candidates,
    main,
    mirror_planes,
)
from torchfit.render import RenderMesh, full_window, render_silhouettes
from torchfit.rotation import axis_angle_to_quat, quat_to_matrix
from torchfit.search import Candidates, fit
from torchfit.shape import load_shape


def _candidate(depth=1.4, dtype=torch.float64):
    quat = axis_angle_to_quat(torch.tensor([[0.4, -1.1, 0.7]], dtype=dtype))
    return Candidates(quat, torch.zeros(1, 3, dtype=dtype), torch.tensor([[0.1, -0.05, depth]], dtype=dtype),
                      torch.tensor([[0.3, -1.0, 0.2]], dtype=dtype), torch.tensor([[4.0, -6.0, 9.0]], dtype=dtype),
                      torch.tensor([[0.1, 0.05]], dtype=dtype))


def test_mirror_planes_of_the_tshape_and_a_box():
    tshape = load_shape(primitive="tshape", density=600.0)
    planes = mirror_planes(tshape)
    # crossbar along x, stem along y: mirror in x and in z, not in y
    assert [int(np.argmin(np.diag(m))) for m in planes] == [0, 2]
    assert len(mirror_planes(load_shape(primitive="box", density=600.0))) == 3


def test_flipped_motion_is_the_mirrored_motion():
    """R'(t) = S R(t) M with ω' = -S ω: a torque-free rotation again (wrong sign of ω' fails)."""
    shape = load_shape(primitive="tshape", density=600.0)
    body = RigidBody.from_shape(shape, torch.float64)
    mirror = torch.as_tensor(mirror_planes(shape)[0])
    cands = _candidate()
    flipped = flip_candidates(cands, mirror)
    ray = cands.com[0] / cands.com[0].norm()
    reflect = torch.eye(3, dtype=torch.float64) - 2 * torch.outer(ray, ray)
    times = torch.linspace(0, 0.6, 25, dtype=torch.float64)
    original = integrate(cands.state(body), times, body, cands.gravity(9.81), step_size=1e-3)
    mirrored = integrate(flipped.state(body), times, body, flipped.gravity(9.81), step_size=1e-3)
    expected = reflect @ original.rot[0] @ mirror
    assert torch.allclose(mirrored.rot[0], expected, atol=1e-6)
    # the centre of mass follows the same parabola
    com = torch.as_tensor(shape.com)
    assert torch.allclose(mirrored.rot[0] @ com + mirrored.position[0], original.rot[0] @ com + original.position[0],
                          atol=1e-9)


def test_flip_keeps_the_silhouette_far_away_and_changes_it_near():
    shape = load_shape(primitive="tshape", density=600.0)
    body = RigidBody.from_shape(shape, torch.float64)
    mesh = RenderMesh.from_shape(shape, torch.float64)
    mirror = torch.as_tensor(mirror_planes(shape)[0])
    from torchfit.camera import Camera

    def iou_at(depth, focal):
        camera = Camera(focal, focal, 159.5, 119.5, 320, 240)
        cands = _candidate(depth)
        masks = []
        for c in (cands, flip_candidates(cands, mirror)):
            state = c.state(body)
            rot = quat_to_matrix(state[:, 3:7])[:, None]
            masks.append(render_silhouettes(mesh, camera, rot, state[:, None, 0:3],
                                            full_window(camera, 1, 1, dtype=torch.float64), size=(240, 320),
                                            sigma=None)[0, 0] > 0.5)
        return float((masks[0] & masks[1]).sum() / (masks[0] | masks[1]).sum())

    # nearly orthographic (far, long lens): the same silhouette; close: perspective tells them apart
    assert iou_at(40.0, 40.0 * 400) > 0.97
    assert iou_at(0.5, 200.0) < 0.95


def test_corner_track_follows_the_symmetric_corner():
    shape = load_shape(primitive="tshape", density=600.0)
    rot = quat_to_matrix(axis_angle_to_quat(torch.tensor([[0.2, 0.3, -0.4]], dtype=torch.float64)))
    trans = torch.tensor([[0.0, 0.1, 1.5]], dtype=torch.float64)
    corner = torch.tensor([0.1, -0.015, 0.015], dtype=torch.float64)
    identity, half_turn = torch.as_tensor(shape.symmetries)
    assert torch.allclose(corner_track(rot, trans, corner, shape, identity), rot @ corner + trans)
    # the T's half turn about its stem maps this corner onto the opposite crossbar end's
    other = torch.tensor([-0.1, -0.015, -0.015], dtype=torch.float64)
    assert torch.allclose(corner_track(rot, trans, corner, shape, half_turn), rot @ other + trans, atol=1e-9)


def test_snapshot_hook_sees_every_stage_and_changes_nothing():
    from torchfit.run import build_problem
    from torchfit.video import load_observation

    rec = load_recording("tshape_small")
    observation = load_observation(str(rec.video), camera=rec.camera)
    problem, _ = build_problem(observation, rec.shape, rec.camera, g=9.81, dtype=torch.float32, device="cpu")
    settings = search_settings(True, 0)
    seen = []
    with_hook = fit(problem, settings, snapshot=lambda stage, cands, losses: seen.append(
        (stage, len(cands), float(losses.min()))))
    without = fit(problem, settings)
    assert [s[0] for s in seen] == ["seeds"] + [f"refine {i + 1}" for i in range(len(settings.stages))] + ["polish"]
    assert seen[-1][2] == pytest.approx(float(with_hook.losses[0]))
    assert torch.equal(with_hook.state, without.state)


def test_bad_recording_names_raise():
    with pytest.raises(ValueError, match="must be one of"):
        load_recording("teapot")
    with pytest.raises(ValueError, match="not a T-handle"):
        main("unused", recording="box_fast", progress=None)


def test_quick_run_writes_figures_and_summary(tmp_path):
    summary = main(tmp_path, quick=True, progress=None)
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
    for name in summary["figures"].values():
        assert (tmp_path / name).stat().st_size > 10_000
    assert [s["stage"] for s in summary["stages"]] == ["seeds", "refine 1", "refine 2", "polish"]
    assert summary["stages"][-1]["mean_iou"] > summary["stages"][0]["mean_iou"]
    assert summary["mean_iou_observed"] > 0.6 and summary["rotation_error_deg"]["max"] < 15
    assert summary["corner_error_px"]["mean"] < 5
    flip = summary["flip"]
    assert flip["loss_after_refit"] <= flip["loss_at_construction"]
    # the flip is a genuinely different orientation, not the fit again
    assert flip["rotation_from_best_deg_t0"] > 30
    assert all(math.isfinite(a["loss"]) for a in summary["alternatives"])
