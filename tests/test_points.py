"""3D point tracks: the CSV and SpinDOE loaders, the point-mass fit, and the points CLI."""

import json
import math
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.discover import PointsProblem, discover_points, fit_points
from torchfit.points import (
    PointModel,
    batch_tracks,
    fit_tracks,
    load_points,
    load_spindoe,
    split_at_impacts,
    synthesize_track,
    write_points,
)

SPINDOE = Path("/work/shared/data/spindoe/trajectories.zip")
AREA, MASS = math.pi * 0.02 ** 2, 0.0027
BALL = {"area": AREA, "mass": MASS, "moment": 2 / 3 * MASS * 0.02 ** 2}


def test_load_points_comma_semicolon_and_header(tmp_path):
    (tmp_path / "a.csv").write_text("t,x,y,z\n" + "\n".join(f"{i / 100},{i},{0},{-i}" for i in range(8)))
    (tmp_path / "b.csv").write_text("\n".join(f"{i / 100};{i};{0};{-i}" for i in range(8)))
    a, b = load_points(tmp_path / "a.csv"), load_points(tmp_path / "b.csv", spin=[1, 2, 3])
    assert a.positions.shape == (8, 3) and np.allclose(a.positions, b.positions) and a.spin is None
    assert np.allclose(b.spin, [1, 2, 3])


@pytest.mark.parametrize("text, match", [
    ("t,x,y,z\n0,0,0,0\n0.1,0,0,0\n0.1,1,1,1\n" + "".join(f"{i},0,0,0\n" for i in range(1, 6)),
     "row 4 has t=0.1 after t=0.1"),
    ("t,x,y,z\n" + "".join(f"{i},0,0,0\n" for i in range(3)), "3 points, need at least 6"),
    ("t,x,y,z\n" + "".join(f"{i},0,0,0\n" for i in range(6)) + "7,0,nan,0\n", "row 8 has a value that is not a finite"),
    ("t,x,y,z\n" + "".join(f"{i},0,0\n" for i in range(6)), "row 2 has 3 columns"),
    ("t,x,y,z\n0,0,0,0\nfoo,1,2,3\n", "row 3 is not four numbers"),
])
def test_load_points_errors_name_file_and_row(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        load_points(path)
    assert "bad.csv" in str(info.value)


def test_load_points_missing_file_and_bad_spin(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_points(tmp_path / "none.csv")
    path = tmp_path / "ok.csv"
    write_points(synthesize_track(samples=10), path)
    with pytest.raises(ValueError, match="data.spin must be three"):
        load_points(path, spin=[1.0, 2.0])


def test_split_at_impacts_finds_a_table_bounce():
    flight = synthesize_track(velocity=(0.0, -5.0, -1.0), position=(0.0, 1.0, 0.3), samples=60, noise=0.0005)
    z = flight.positions[:, 2]
    first = int(np.argmax(z < 0))  # reflect below the table: a bounce with restitution 1
    positions = flight.positions.copy()
    positions[first:, 2] = np.abs(z[first:])
    pieces = split_at_impacts(flight.__class__(flight.times, positions, flight.spin, "bounce"))
    assert len(pieces) == 2 and pieces[1].meta["after"] == "bounce"
    assert abs(len(pieces[0]) - first) <= 1


def test_point_fit_recovers_drag_and_lift():
    true = {("quadratic_drag", "drag_coefficient"): 0.45, ("magnus", "lift_coefficient"): 0.8}
    tracks = [synthesize_track(["quadratic_drag", "magnus"], true, velocity=v, spin=w, seed=i, samples=50)
              for i, (v, w) in enumerate([((4.0, 0.5, 2.0), (0.0, -100.0, 20.0)), ((-3.0, 2.0, 1.0), (50.0, 0.0, 80.0))])]
    data = batch_tracks(tracks)
    model = PointModel(["quadratic_drag", "magnus"], spin_known=True, **BALL)
    problem = PointsProblem(data, **BALL)
    fit = fit_tracks(model, data, problem.start(model, None, "all"))
    cd, cl = fit.params[0, 6:].tolist()
    std = torch.sqrt(torch.diagonal(fit.shared_covariance) * problem.noise_var)
    assert abs(cd - 0.45) < 4 * float(std[0]) + 0.01 and abs(cl - 0.8) < 4 * float(std[1]) + 0.01
    assert math.sqrt(fit.rss / fit.n_obs) < 1.2e-3  # at the 1 mm noise


def test_backcast_predicts_each_tracks_start_from_the_rest():
    """PointsProblem(backcast=True): the first quarter of each track is held out as well, fitted
    without it and predicted; the held-out RMS is the mean of the two parts'. Moving the first
    quarter's samples leaves the backcast's fit as it was (it does not see them) and moves the
    end's fit (which does)."""
    tracks = [synthesize_track(["quadratic_drag"], {("quadratic_drag", "drag_coefficient"): 0.5}, samples=n, seed=k)
              for k, n in enumerate((40, 33))]
    data = batch_tracks(tracks)
    forward = PointsProblem(data, candidates=("quadratic_drag",), noise_var=1e-6, **BALL)
    both = PointsProblem(data, candidates=("quadratic_drag",), noise_var=1e-6, backcast=True, **BALL)
    start_test, start_train = both.splits["train_backcast"][1], both.splits["train_backcast"][0]
    assert start_test.weights.sum(-1).tolist() == [10, 9]  # ceil(0.25 n) of 40 and 33 samples
    assert torch.equal(start_test.weights + start_train.weights, data.weights)
    assert torch.all(start_test.weights[:, :9] == 1)
    one, two = forward.fit(("quadratic_drag",), None), both.fit(("quadratic_drag",), None)
    assert two.rss == pytest.approx(one.rss, rel=1e-12)  # the fit to all samples is the same
    start_fit = two.payload["train_backcast"]
    held = start_fit.residual * start_test.weights.unsqueeze(-1)
    start_rms = math.sqrt(float((held ** 2).sum()) / (3 * float(start_test.weights.sum())))
    assert two.heldout_rms == pytest.approx((one.heldout_rms + start_rms) / 2, rel=1e-9)
    assert len(two.heldout_params) == 2 and set(two.heldout_params[1]) == {"quadratic_drag"}

    moved = data.positions.clone()
    moved[start_test.weights > 0] += torch.tensor([0.05, -0.03, 0.02], dtype=moved.dtype)
    shifted = PointsProblem(replace(data, positions=moved), candidates=("quadratic_drag",), noise_var=1e-6,
                            backcast=True, **BALL).fit(("quadratic_drag",), None)
    # to the fit's convergence, not to rounding: at rtol 1e-9 this failed once in a full pytest run on a
    # loaded machine (2026-11-29) and passed alone; the cause was not found. The held-out start,
    # moved 5 cm against 1 mm noise, would move these parameters by far more than 1e-6
    assert torch.allclose(shifted.payload["train_backcast"].params, start_fit.params, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(shifted.payload["train"].params, two.payload["train"].params, rtol=1e-6)
    assert shifted.heldout_rms > two.heldout_rms + 0.01  # the start, 6 cm off, is predicted badly


def test_held_out_median_over_tracks_is_not_dominated_by_one_bad_track():
    """``ModelFit.heldout_track_median``: the median over tracks of each track's held-out RMS (the
    mean over the splits, as ``heldout_rms``). One of five tracks whose held-out end is moved 5 cm
    (samples no fit sees) raises the pooled held-out RMS many times over; the median is the clean
    tracks' own figure, near the 1 mm noise. With the backcast both figures are the mean of the
    two splits', each as defined here from the fits' residuals."""
    from torchfit.discover import track_median_rms

    tracks = [synthesize_track(["quadratic_drag"], {("quadratic_drag", "drag_coefficient"): 0.5}, samples=40, seed=k)
              for k in range(5)]
    data = batch_tracks(tracks)

    def per_track(fit, split):
        held = fit.payload[split[0]].residual * split[1].weights.unsqueeze(-1)
        return held, np.array([math.sqrt(float((held[b] ** 2).sum()) / (3 * float(split[1].weights[b].sum())))
                               for b in range(len(tracks))])

    problem = PointsProblem(data, candidates=(), noise_var=1e-6, **BALL)
    clean = problem.fit(("quadratic_drag",), None)
    end_test = problem.splits["train"][1]
    moved = data.positions.clone()
    moved[0][end_test.weights[0] > 0] += torch.tensor([0.05, 0.0, 0.0], dtype=moved.dtype)
    bad = PointsProblem(replace(data, positions=moved), candidates=(), noise_var=1e-6, **BALL).fit(("quadratic_drag",), None)
    assert bad.heldout_rms > 5 * clean.heldout_rms
    _, clean_rms = per_track(clean, ("train", end_test))
    assert clean.heldout_track_median == pytest.approx(np.median(clean_rms), rel=1e-12)
    assert clean.heldout_track_median < 3e-3  # about the 1 mm noise
    # the train fit never saw the moved samples: the other four tracks' figures are as they were
    assert bad.heldout_track_median == pytest.approx(np.median(np.r_[np.inf, clean_rms[1:]]), rel=1e-9)

    both = PointsProblem(data, candidates=(), noise_var=1e-6, backcast=True, **BALL)
    fit = both.fit(("quadratic_drag",), None)
    medians = []
    for split in both.splits.items():
        held, rms = per_track(fit, (split[0], split[1][1]))
        medians.append(float(np.median(rms)))
        assert track_median_rms(held, split[1][1].weights) == pytest.approx(medians[-1], rel=1e-12)
    assert fit.heldout_track_median == pytest.approx(np.mean(medians), rel=1e-12)
    # one track: no median to take (the pooled figure is that track's); no weighted sample: NaN
    single = PointsProblem(batch_tracks(tracks[:1]), candidates=(), noise_var=1e-6, **BALL)
    assert single.fit((), None).heldout_track_median is None
    assert math.isnan(track_median_rms(held, torch.zeros_like(end_test.weights)))


def test_fit_points_writes_result(tmp_path):
    data = batch_tracks([synthesize_track(samples=30)])
    content = fit_points(data, out_dir=tmp_path, **BALL)
    assert json.loads((tmp_path / "result.json").read_text())["rms_m"] == pytest.approx(content["rms_m"])
    assert content["rms_m"] < 1.5e-3 and (tmp_path / "residuals.png").stat().st_size > 0
    assert np.allclose(content["params"]["position"], [0.0, 0.0, 0.3], atol=3e-3)


@pytest.mark.skipif(not SPINDOE.exists(), reason="SpinDOE data not present")
def test_spindoe_loader_and_discover_on_three_trajectories():
    tracks = load_spindoe(SPINDOE, limit=4)
    assert len(tracks) >= 3
    tracks = tracks[:3]
    for track in tracks:
        assert track.meta["piece"] == 0 and track.spin.shape == (3,)
        assert np.all(np.diff(track.times) > 0) and len(track) >= 8
        assert track.positions[:, 2].min() > -0.05  # before the bounce: above the table
    data = batch_tracks(tracks)
    content = discover_points(data, candidates=["quadratic_drag", "linear_drag", "time_scale"], **BALL)
    assert content["verdict"][:1] == ["quadratic_drag"]
    cd = content["models"][1]["params"]["quadratic_drag"]["drag_coefficient"]["value"]
    assert 0.3 < cd < 0.8


def test_spindoe_loader_errors(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_spindoe(tmp_path / "none.zip")
    bad = tmp_path / "bad.zip"
    with zipfile.ZipFile(bad, "w") as archive:
        archive.writestr("x/000.csv", "0;0;0;0\n")
    with pytest.raises(ValueError, match="has no index.csv"):
        load_spindoe(bad)
