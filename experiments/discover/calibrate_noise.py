"""Calibrate the video noise model on recordings that hide nothing.

    python experiments/discover/calibrate_noise.py [names...]     # ~2-3 min per recording
    python experiments/discover/calibrate_noise.py --true-masks [names...]  # the engine's exact masks
    python experiments/discover/calibrate_noise.py --albedo-passes N [names...]  # SegmentationSettings.albedo_passes N
    python experiments/discover/calibrate_noise.py --exposure [names...]  # the data.exposure path
    python experiments/discover/calibrate_noise.py --exposure --scale 2 [names...]  # through a camera of twice the pixels
    python experiments/discover/calibrate_noise.py --exposure --sharp [names...]  # the throws without motion blur

For each shipped MuJoCo recording (nothing missing: the model is exact up to segmentation):

* the frame-to-frame correlation of the segmentation error: the five residual channels of the
  segmented masks against the true masks (``masks.npz``), their lag-one and lag-two
  autocorrelation (``discover_video.FRAME_CORRELATION`` is the lag-one value, AR(1));
* the edge term of the noise floor: fit the baseline as discover does and print the chi-squared
  per observation of its whitened channel residuals for several ``edge_px`` values of the floor
  (jitter ⊕ edge term). The rule: the grid value that brings the largest chi-squared to about 1
  is the one discover uses (``discover_video.EDGE_PX``).

The concealed set's controls are *not* used here, so they stay an independent check. Writes
results/noise_calibration.json.

With ``--true-masks`` the recordings' exact masks (``masks.npz``) stand in for the segmentation
and the edge term's grid goes lower (``EXACT_EDGES``): the floor for masks without segmentation
error (``discover_video``'s ``edge_px`` argument, ``params.edge_px`` on the command line). Writes
results/noise_calibration_true_masks.json (no autocorrelation: there is no segmentation error).

With ``--exposure`` the baseline is the one of the ``data.exposure`` path as ``concealed.py
--albedo-passes 1 --exposure --fit-exposure`` runs it: the albedo pass (unless ``--albedo-passes``
says otherwise), the frames' soft coverage against the silhouette averaged over the recording's
own exposure (``truth.json``'s render), its fraction fitted. The edge term's grid goes lower
(``EXPOSURE_EDGES``). Writes results/noise_calibration_albedo1_exposure_fitted.json. The
autocorrelation is still the masks' against the true masks.

With ``--scale N`` the shipped recordings' throws are made again through a camera with N times the
pixels along each side, the same field of view (``make_concealed.scaled_spec``, as the concealed
sets' ``--scale``), in recordings_shipped_x<N>/ beside this script (made once, then reused), and
calibrated there; the results file gets ``_x<N>``. The segmentation takes its defaults for that
camera (``coverage_near_px=auto``: 8 steps at 1280 x 960).

With ``--sharp`` the throws are made again without motion blur (one render per frame,
``make_concealed.sharp_spec``, as the concealed sets' ``--sharp``), in recordings_shipped_sharp/
(``_sharp_x<N>/`` with ``--scale N``), and the results file gets ``_sharp``: the edge term of a
camera with a short exposure.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from concealed import recording_exposure
from true_masks import load_problem

from torchfit.discover_video import FRAME_CORRELATION, VideoProblem
from torchfit.losses import mask_moments
from torchfit.paper._recording import Recording, load_recording, recording_from_folder
from torchfit.residuals import CHANNELS, channel_values, noise_floor, systematic_floor
from torchfit.video import SegmentationSettings

EDGES = (0.5, 0.4, 0.3, 0.25, 0.2, 0.15, 0.1)
EXACT_EDGES = (0.1, 0.07, 0.05, 0.04, 0.03, 0.02, 0.01, 0.0)
EXPOSURE_EDGES = (0.4, 0.3, 0.25, 0.2, 0.15, 0.1, 0.07, 0.05, 0.04, 0.03)
HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


def remade_recording(name: str, scale: int, sharp: bool = False) -> Recording:
    """The shipped recording ``name``'s throw through a camera with ``scale`` times the pixels along
    each side (``make_concealed.scaled_spec``), without motion blur if ``sharp``
    (``make_concealed.sharp_spec``), made in ``recordings_shipped[_sharp][_x<scale>]/`` the first
    time and read from there after."""
    folder = HERE / ("recordings_shipped" + ("_sharp" if sharp else "") + (f"_x{scale}" if scale > 1 else "")) / name
    if not (folder / "truth.json").exists():
        sys.path.insert(0, str(HERE.parent / "recordings"))
        import make_concealed
        import make_recordings as mr

        specs = {spec.name: spec for spec in mr.shipped_specs()}
        if name not in specs:
            raise SystemExit(f"no shipped recording {name!r}; choose from {sorted(specs)}")
        mr.offscreen_gl()
        spec = make_concealed.scaled_spec(specs[name], scale)
        mr.make_recording(make_concealed.sharp_spec(spec) if sharp else spec, folder.parent)
    return recording_from_folder(name, folder)


def edge_by_rule(results: dict) -> float:
    """The edge term the calibration gives: of ``results`` (this script's file, throw name -> its
    ``calibrate`` output), the grid value whose largest chi-squared per observation over the throws
    (each the mean over the five channels) is nearest 1."""
    edges = list(next(iter(results.values()))["rows"])
    worst = {e: max(r["rows"][e]["chi2_per_obs"] for r in results.values()) for e in edges}
    return float(min(edges, key=lambda e: abs(worst[e] - 1.0)))


def correlation(rec, observation, lags=(1, 2)) -> dict:
    """Per channel, the autocorrelation of segmented minus true masks' channels at ``lags`` frames."""
    true = np.load(rec.folder / "masks.npz")["masks"].astype(bool)
    channels = channel_values(mask_moments(torch.as_tensor(observation.masks, dtype=torch.float64)),
                              mask_moments(torch.as_tensor(true, dtype=torch.float64)))
    out = {}
    for c in CHANNELS:
        v = channels[c].numpy()[observation.used]
        v = v - v.mean()
        out[c] = [float(np.sum(v[:-k] * v[k:]) / np.sum(v * v)) for k in lags]
    return out


def calibrate(name: str, true_masks: bool = False, settings: SegmentationSettings | None = None,
              exposure: bool = False, scale: int = 1, sharp: bool = False) -> dict:
    rec = load_recording(name) if scale == 1 and not sharp else remade_recording(name, scale, sharp)
    observation, problem, span = load_problem(rec.folder, rec.shape, rec.camera, true_masks, settings)
    blur = {}
    if exposure:  # the data.exposure path: the soft coverage against the recording's exposure, fitted
        # a sharp throw has no renderer's exposure to start from: 0.5 of the interval, a camera's
        # (no sub-frames), as the default's runs start (concealed.py --exposure-fraction 0.5 --exposure-taps 0)
        start = recording_exposure(rec.truth, 0.5, 0) if sharp else recording_exposure(rec.truth)
        blur = {"exposure": start, "fit_exposure": True,
                "coverage": torch.as_tensor(observation.coverage_moments[span])}
    video = VideoProblem(problem, candidates=(), **blur)
    base = video.fit((), None)
    channels = base.payload["channels"]
    used = video.problem.used.cpu().numpy().astype(bool)
    masks = video.problem.masks.cpu().numpy() > 0.5
    jitter = {c: noise_floor(channels[c][used], FRAME_CORRELATION) for c in CHANNELS}
    rows = {}
    for edge in EXACT_EDGES if true_masks else EXPOSURE_EDGES if exposure else EDGES:
        system = systematic_floor(masks, used, edge)
        video.noise = {c: float(np.hypot(jitter[c], system[c])) for c in CHANNELS}
        chi2 = {c: float(np.nanmean(v**2)) for c, v in video.whitened_channels(channels, used).items()}
        rows[str(edge)] = {"chi2_per_obs": float(np.mean(list(chi2.values()))), "per_channel": chi2}
    if true_masks:
        return {"jitter": jitter, "rows": rows}
    out = {"jitter": jitter, "rows": rows, "autocorrelation_lag1_lag2": correlation(rec, observation)}
    if exposure:
        out["exposure_fitted"] = base.payload.get("exposure")
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", default=["tshape", "tshape_intermediate", "box_fast", "cylinder"])
    ap.add_argument("--true-masks", action="store_true", help="the engine's exact masks instead of the segmentation")
    ap.add_argument("--albedo-passes", type=int, metavar="N", help="segment with SegmentationSettings.albedo_passes N")
    ap.add_argument("--exposure", action="store_true",
                    help="the data.exposure path: the soft coverage against the recording's exposure, fitted "
                         "(with the albedo pass unless --albedo-passes says otherwise)")
    ap.add_argument("--scale", type=int, default=1, metavar="N",
                    help="the shipped throws made again through a camera with N times the pixels along each side")
    ap.add_argument("--sharp", action="store_true", help="the shipped throws made again without motion blur")
    args = ap.parse_args()
    if args.scale < 1:
        ap.error(f"--scale needs a whole factor >= 1, got {args.scale}")
    exact, passes, names, blur = args.true_masks, args.albedo_passes, args.names, args.exposure
    if passes is not None and (exact or passes < 0):
        ap.error(f"--albedo-passes needs a count >= 0 and segmented masks, got {passes}")
    if blur and exact:
        ap.error("--exposure needs the segmentation's soft coverage, not --true-masks")
    if blur and passes is None:
        passes = 1  # as data.exposure turns it on
    OUT = RESULTS / ("noise_calibration" + ("_true_masks" if exact else "")
                     + (f"_albedo{passes}" if passes is not None else "")
                     + ("_exposure_fitted" if blur else "") + ("_sharp" if args.sharp else "")
                     + (f"_x{args.scale}" if args.scale > 1 else "")
                     + ".json")
    settings = None if passes is None else SegmentationSettings(albedo_passes=passes)
    for name in names:
        result = calibrate(name, exact, settings, blur, args.scale, args.sharp)
        print(name, {e: round(r["chi2_per_obs"], 3) for e, r in result["rows"].items()}, "max over channels",
              {e: round(max(r["per_channel"].values()), 3) for e, r in result["rows"].items()}, flush=True)
        if not exact:
            print("  lag-1/lag-2 correlation",
                  {c: [round(x, 2) for x in v] for c, v in result["autocorrelation_lag1_lag2"].items()}, flush=True)
        OUT.parent.mkdir(parents=True, exist_ok=True)
        results = json.loads(OUT.read_text()) if OUT.exists() else {}  # other runs may have written
        OUT.write_text(json.dumps(results | {name: result}, indent=1))
    stored = json.loads(OUT.read_text())
    print(f"edge term by the rule over {sorted(stored)}: {edge_by_rule(stored):g} px")
