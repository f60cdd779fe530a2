"""Diagnostics behind the sections of experiments/discover/HISTORY.md *The exact masks of fresh set 2, and the
scoreboard* and *What limits the video: four checks*.

    python experiments/discover/diagnose.py segmentation SET NAME...   # segmented minus true masks per frame, ~1 min each
    python experiments/discover/diagnose.py clock SET NAME             # the clock refit from other starts, ~3 min
    python experiments/discover/diagnose.py stall SET NAME EFFECT      # is the baseline stalled? ~4 min
    python experiments/discover/diagnose.py jacobian SET NAME          # the Jacobian against the earlier ways of computing it, ~3 min
    python experiments/discover/diagnose.py coverage SET NAME...       # channels from the soft coverage vs the mask, ~20 s each
    python experiments/discover/diagnose.py heldout SET NAME EFFECT    # is the held-out fit where its frames put it? ~9 min
    python experiments/discover/diagnose.py heldout-channels SET NAME EFFECT [robust=K] [backcast=true] [masks=true]  # the held-out prediction per channel (masks=true: the engine's), ~2 min
    python experiments/discover/diagnose.py heldout-blur SET NAME EFFECT [exposure=F] [robust=K] [backcast=true] [SETTING=V...]  # the same with the exposure fitted from 0.5 (a camera's) or held at F, ~3 min
    python experiments/discover/diagnose.py heldout-swap SET NAME EFFECT [backcast=true]  # true masks on the held-out (backcast=true: the first quarter) or train frames, ~6 min
    python experiments/discover/diagnose.py chroma W...                # segmentation error at chroma weights W, all 54, ~7 s each
    python experiments/discover/diagnose.py sets SET...                # segmentation error per set, default settings, ~7 s each
    python experiments/discover/diagnose.py lens-masks DIR NAME...     # true masks against the mesh projected through the lens, ~5 s each
    python experiments/discover/diagnose.py sources FRESH NAME...      # the recording remade without each source of error, ~1 min each
    python experiments/discover/diagnose.py blur SET NAME... [SETTING=V...]  # coverage moments against the exposure's average, ~30 s each
    python experiments/discover/diagnose.py blur-estimate SET NAME... [SETTING=V...]  # the exposure read from the blur alone, ~25 s each
    python experiments/discover/diagnose.py blur-speed SET NAME... [SETTING=V...]  # the coverage's blur reading against the speed, per band, ~30 s each
    python experiments/discover/diagnose.py area SET NAME... [SETTING=V...]  # the coverage's area per frame against the background's contrast, ~30 s each
    python experiments/discover/diagnose.py spread-stall SET NAME... [SETTING=V...]  # the baseline with a point spread (1 ± 1 px², none) and 45 more LM iterations, ~6 min each
    python experiments/discover/diagnose.py error-speed SET NAME... [SETTING=V...]  # the segmentation's error per channel against the speed, masks and coverage, ~20 s each
    python experiments/discover/diagnose.py shape-frames SET NAME... [SETTING=V...]  # the coverage's area and variance excess per frame against the exact exposure average, ~20 s each
    python experiments/discover/diagnose.py baseline-starts SET NAME... [SETTING=V...]  # the baseline's LM from each of the search's first 4 candidates, ~3 min each
    python experiments/discover/diagnose.py exact-coverage SET NAME... [SETTING=V...] [parts=area,centroid,shape|spread|stretch]  # discover with the exposure on a coverage partly exact, ~8 min each
    python experiments/discover/diagnose.py stretch SET NAME...        # the masks' stretch along the motion against the speed, ~10 s each
    python experiments/discover/diagnose.py contrast SET NAME...       # does the outline's contrast flag the bad frames? ~10 s each
    python experiments/discover/diagnose.py clip SET NAME...           # what blur does to a ball's 0.5 contour, by geometry alone, ~1 s each
    python experiments/discover/diagnose.py stretch-sources FRESH NAME...  # the same, remade without motion blur, ~1 min each
    python experiments/discover/diagnose.py ramp FRESH NAME [SOURCE...] [SETTING=V...]  # coverage on a blurred edge's ramp against the truth, ~1 min each
    python experiments/discover/diagnose.py codec FRESH NAME...        # remade with other H.264 encodings (CODECS), ~2 min each
    python experiments/discover/diagnose.py search SET NAME... SETTING=V...  # the search on default and on changed masks, ~2 min each
    python experiments/discover/diagnose.py exposure SET NAME... [SETTING=V...] [fractions=F1,F2,...]  # the baseline at other exposures than the recording's (default 0, 0.25, 0.5, 0.75, 1), ~2 min each
    python experiments/discover/diagnose.py regions SET NAME... [SETTING=V...]  # the coverage's centroid error by region (interior, ramp, outside), ~30 s each
    python experiments/discover/diagnose.py contrast-oracle SET NAME... [SETTING=V...]  # that error with the low-contrast pixels made exact (an oracle's floor), ~30 s each
    python experiments/discover/diagnose.py lens-residual SET NAME... [SETTING=V...]  # a lens left after undistortion? ~20 s each
    python experiments/discover/diagnose.py regions-sources FRESH NAME...  # regions on the recording remade without each source of error, ~6 min each
    python experiments/discover/diagnose.py gravity-known SET NAME     # discover as by default with gravity held at the engine's, ~1-2 min
    python experiments/discover/diagnose.py frame-correlation SET [SET...]  # the segmentation error's lag-one correlation on each set's controls, ~30 s a recording
    python experiments/discover/diagnose.py jump-scores SET NAME...     # the jump test's score per channel and frame, as the default meets them, ~1 min each
    python experiments/discover/diagnose.py resegment SET NAME...       # the segmentation's error against that of a composite of the exact coverage, segmented the same way, ~1 min each
    python experiments/discover/diagnose.py end-frames SET [SETTING=V...]  # the coverage's error on a clip's first and last frames, the default's segmentation and each SETTING=V's, ~15 s a recording each

SET is a folder of concealed recordings beside this file (``recordings``, ``recordings_fresh2``).
Each prints its figures and writes them to results/diagnose_<command>_<set>_<name>.json
(``chroma``: results/diagnose_chroma.json; ``sets``: results/diagnose_sets.json; ``lens-masks``: results/diagnose_lens_masks.json; ``sources``, ``stretch-sources`` and ``regions-sources``:
results/diagnose_[stretch_|regions_]sources.json; ``ramp``: results/diagnose_ramp.json; ``codec``:
results/diagnose_codec.json. FRESH is the set's number, 0 for the first; these five need MuJoCo,
the ``recordings`` extra).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from concealed import CANDIDATES, recording_exposure
from segmentation_error import frame_errors, mask_centroids, measure, segment_watching
from true_masks import load_problem, problem_of, recording_parts, subframe_times, with_masks

import torchfit.discover_video as dv
from torchfit.losses import raw_from_central
from torchfit.rotation import quat_to_matrix, rotation_angle
from torchfit.search import Exposure, SearchSettings, candidate_losses
from torchfit.search import fit as search_fit
from torchfit.video import SegmentationSettings, load_observation, mask_velocity

HERE = Path(__file__).resolve().parent


def _video(folder: Path, true_masks: bool = False, **settings) -> dv.VideoProblem:
    """The recording's VideoProblem on its segmented masks (``true_masks``: the engine's)."""
    _, shape, camera = recording_parts(folder)
    _, problem, _ = load_problem(folder, shape, camera, true_masks)
    return dv.VideoProblem(problem, **settings)


def segmentation(folder: Path) -> dict:
    """Per frame: the segmented mask's centroid minus the true one's (px) and its edge bias
    (:func:`segmentation_error.measure`), with the edge bias's mean and spread; the true masks'
    centroid speed (px per frame, central differences) and its correlation with the edge bias
    (motion blur reads a fast silhouette's size otherwise than a slow one's)."""
    frames = measure(folder)["frames"]
    edge = [r["edge_px"] for r in frames]
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    speed = np.hypot(*np.gradient(mask_centroids(true), axis=0).T)
    return {"dx_px": [r["dx"] for r in frames], "dy_px": [r["dy"] for r in frames], "edge_px": edge,
            "edge_mean": float(np.mean(edge)), "edge_sd": float(np.std(edge)), "speed_px": speed.tolist(),
            "edge_speed_correlation": float(np.corrcoef(edge, speed)[0, 1])}


def clock(folder: Path, starts=(1.0135, 1.02)) -> dict:
    """The baseline, discover's clock refit, and LM (30 iterations) from other clock starts."""
    video = _video(folder)
    base = video.fit((), None)
    refit = video.fit(("time_scale",), base)
    every = video.problem.used.cpu().numpy().astype(bool)
    out = {"baseline_rss": base.rss, "baseline_edge": list(base.payload["model"].nuisances),
           "refit_rss": refit.rss, "refit_clock": refit.params["time_scale"]["time_scale"],
           "refit_edge": list(refit.payload["model"].nuisances), "starts": {}}
    for start_clock in starts:
        start = video._extend(base.payload["model"], ("time_scale",))
        start.values["time_scale"]["time_scale"] = torch.tensor(start_clock, dtype=torch.float64)
        model, resid, _ = video._lm(start, every, 30)
        out["starts"][start_clock] = {"cost": video._cost(resid), "edge": list(model.nuisances),
                                      "clock": float(model.values["time_scale"]["time_scale"])}
    return out


def stall(folder: Path, effect: str) -> dict:
    """Whether the baseline is where LM stops: its cost after 75 more iterations, and the cost the
    baseline model reaches from ``effect``'s refit with that effect removed (45 iterations)."""
    video = _video(folder)
    base = video.fit((), None)
    every = video.problem.used.cpu().numpy().astype(bool)
    model, resid, _ = video._lm(base.payload["model"], every, 75)
    refit = video.fit((effect,), base)
    point = refit.payload["model"]
    _, from_refit, _ = video._lm(dv._Model(point.cands, {}, point.nuisances), every, 45)
    return {"baseline_rss": base.rss, "after_75_more": video._cost(resid), "refit_rss": refit.rss,
            "refit_wald": refit.wald, "from_refit_without_effect": video._cost(from_refit)}


def _column_by_column(video: dv.VideoProblem, model, mask: torch.Tensor, step: float = 1e-3) -> torch.Tensor:
    """The Jacobian as the code before ``0939874`` computed it: all 14 state columns in one batch,
    then each extra column (effect parameters and edge terms) by its own flight and render, then
    the held-fixed columns zeroed."""
    n_extra = video._extra_count(model)
    zero = torch.zeros(n_extra, dtype=torch.float64)
    with torch.no_grad():
        state = torch.cat((torch.zeros(1, 14, dtype=torch.float64), step * torch.eye(14, dtype=torch.float64)))
        rows = video._vector(*video._build(model, state, zero), mask)
        columns = [(rows[1:] - rows[0]) / step]
        for j in range(n_extra):
            shifted = zero.clone()
            shifted[j] = step
            moved = video._vector(*video._build(model, torch.zeros(1, 14, dtype=torch.float64), shifted), mask)[0]
            columns.append(((moved - rows[0]) / step)[None])
    jac = torch.cat(columns).T.double()
    jac[:, video._frozen(model)] = 0.0
    return jac


def _effects_one_by_one(video: dv.VideoProblem, model, mask: torch.Tensor, step: float = 1e-3) -> torch.Tensor:
    """The Jacobian as the code before ``b76339b`` computed it, and for a clock's and a lens's
    columns the code before the clock and lens took one value per candidate (2026-11-25): the
    free state columns in one batch, then each effect parameter by its own flight and render, the
    edge bias's two columns reusing the unmoved render."""
    n_extra = video._extra_count(model)
    free = torch.nonzero(~video._frozen(model)[:14]).flatten()
    zero_state, zero_extra = torch.zeros(1, 14, dtype=torch.float64), torch.zeros(n_extra, dtype=torch.float64)
    with torch.no_grad():
        state = torch.zeros(1 + len(free), 14, dtype=torch.float64)
        state[1 + torch.arange(len(free)), free] = step
        fitted = video._fitted_moments(*video._build(model, state, zero_extra)[:2])
        rows = video._vector_of(fitted, model.nuisances, mask)
        jac = rows.new_zeros(rows.shape[1], 14 + n_extra)
        jac[:, free] = ((rows[1:] - rows[0]) / step).T
        for j in range(n_extra):
            shifted = zero_extra.clone()
            shifted[j] = step
            cands, effects, edge = video._build(model, zero_state, shifted)
            moved = (video._vector(cands, effects, edge, mask) if j < n_extra - 2
                     else video._vector_of(tuple(m[:1] for m in fitted), edge, mask))
            jac[:, 14 + j] = (moved[0] - rows[0]) / step
    return jac.double()


def jacobian(folder: Path, repeats: int = 3) -> dict:
    """Seconds per Jacobian, side by side at the recording's baseline with no effect and with
    effects added: column by column (the code before ``0939874``), the effects' parameters one by
    one (the code before ``b76339b``; a clock's and a lens's, before 2026-11-25) and as discover computes it now; and the largest
    difference of each from discover's Jacobian."""
    video = _video(folder)
    base = video.fit((), None)
    mask = video.problem.used
    out = {}
    ways = {"column_by_column": lambda model: _column_by_column(video, model, mask),
            "effects_one_by_one": lambda model: _effects_one_by_one(video, model, mask),
            "discover": lambda model: video._jacobian(model, mask)[1]}
    for effects in ((), ("quadratic_drag",), ("com_offset",), ("lens_distortion",), ("time_scale",),
                    ("magnus", "com_offset"), ("time_scale", "com_offset")):
        model = video._extend(base.payload["model"], effects)
        seconds, jacobians = {label: [] for label in ways}, {}
        for _ in range(2):  # two rounds, best of each
            for label, fn in ways.items():
                clock_ = time.perf_counter()
                for _ in range(repeats):
                    jacobians[label] = fn(model)
                seconds[label].append((time.perf_counter() - clock_) / repeats)
        entry = out["+".join(effects) or "baseline"] = {f"{label}_s": min(seconds[label]) for label in ways}
        entry["max_abs_entry"] = float(jacobians["discover"].abs().max())
        for label in ("column_by_column", "effects_one_by_one"):
            entry[f"{label}_max_abs_difference"] = float((jacobians[label] - jacobians["discover"]).abs().max())
            entry[f"{label}_ratio"] = entry[f"{label}_s"] / entry["discover_s"]
    return out


def coverage(folder: Path) -> dict:
    """The five channels of the segmented mask, and of its soft coverage (the segmentation's
    per-pixel estimate before the 0.5 threshold, clipped to [0, 1], within 4 px of the mask),
    against the true mask's: mean, RMS about the mean and frame-to-frame jitter (second
    differences / sqrt 6) of each, over all frames. Would moments of the coverage be less noisy?"""
    from scipy import ndimage

    from torchfit.losses import mask_moments
    from torchfit.residuals import channel_values

    # the per-pixel coverage, before smoothing and threshold
    masks, kept, true = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage)
    near = np.stack([ndimage.binary_dilation(m, iterations=4) for m in masks])
    truth = mask_moments(torch.as_tensor(true, dtype=torch.float64))
    out = {}
    for label, observed in (("mask", masks), ("coverage", np.clip(np.stack(kept), 0, 1) * near)):
        values = channel_values(mask_moments(torch.as_tensor(observed, dtype=torch.float64)), truth)
        out[label] = {k: {"mean": float(np.mean(v.numpy())), "rms": float(np.std(v.numpy())),
                          "jitter": float(np.std(np.diff(v.numpy(), 2)) / np.sqrt(6))} for k, v in values.items()}
    return out


def heldout(folder: Path, effect: str, scale_factor: str = "3") -> dict:
    """The held-out fit (all frames but the last quarter) of the baseline plus ``effect``: its
    train cost and held-out centroid error as discover leaves it, after 40 more LM iterations
    (with LM's early stop on a relative decrease below 1e-5, and without it),
    and from the all-frames optimum (which has seen the held-out frames: a start discover does not
    use). HISTORY.md's earlier tables have one more row, the effect screened on the train frames
    alone; since d572dc3 discover itself starts the held-out fit from that screening, so that row
    is now the first one. Then the same fits with the
    ``scale`` channel's noise floor times ``scale_factor`` (is the size, i.e. the depth, what
    misleads it?)."""
    def run(factor: float) -> dict:
        video = _video(folder)
        if factor != 1.0:
            original = video._set_noise

            def patched(model, *args, **kwargs):
                original(model, *args, **kwargs)
                video.noise["scale"] *= factor
            video._set_noise = patched
        base = video.fit((), None)
        refit = video.fit((effect,), base)
        train = video.train

        def summary(model, iterations: int, tolerance: float = 1e-5) -> dict:
            model, resid, _ = video._lm(model, train, iterations, tolerance)
            channels = video.residuals(model)
            held = np.hypot(channels["centroid_x"], channels["centroid_y"])[video.held]
            return {"train_cost": video._cost(resid), "heldout_px": float(np.sqrt(np.mean(held**2))),
                    "params": {p: float(torch.as_tensor(v).reshape(-1)[0]) for p, v in model.values[effect].items()},
                    "gravity_angles": model.cands.gravity_angles[0].tolist()}
        return {"all_frames": {p: float(torch.as_tensor(v).reshape(-1)[0])
                               for p, v in refit.payload["model"].values[effect].items()},
                "discover": summary(refit.payload["held_models"][0], 0),
                "40_more": summary(refit.payload["held_models"][0], 40),
                "40_more_without_early_stop": summary(refit.payload["held_models"][0], 40, 0.0),
                "from_all_frames_optimum": summary(refit.payload["model"], 15)}
    return {"noise_as_is": run(1.0), f"scale_noise_times_{scale_factor}": run(float(scale_factor))}


def heldout_channels(folder: Path, effect: str, blurred: bool = False, held_exposure: float | None = None,
                     settings: SegmentationSettings | None = None, robust: float | None = None,
                     backcast: bool = False, true_masks: bool = False) -> dict:
    """Which channel turns a held-out test: discover's baseline and its refit with ``effect``,
    each with its nuisances (the edge bias's two terms, and with ``blurred`` the exposure) and
    effect value fitted on all frames and, per held-out split (``splits``: the end; with
    ``backcast`` the start as well), on that split's train frames, with its held-out prediction
    per channel in noise floors (RMS and mean over the split's held-out frames). ``blurred``
    (command ``heldout-blur``): the coverage against an exposure fitted from 0.5 as a camera's,
    with the albedo pass, as ``concealed.py --albedo-passes 1 --exposure --exposure-fraction 0.5
    --exposure-taps 0 --fit-exposure``; with ``held_exposure`` (``heldout-blur ... exposure=F``) the
    exposure held at F instead, in every fit and held-out fit; ``settings`` (``SETTING=V``, e.g.
    ``coverage_band=motion coverage_clip=false``) the blurred path's segmentation, its albedo pass
    kept unless one of them sets ``albedo_passes``; ``robust`` (``robust=K``): Huber's loss at K noise
    floors in every fit, as the default (``data.exposure=auto``) has it at 2; ``backcast``
    (``backcast=true``): the first quarter held out as well, as the default has it where the blur
    is modelled; ``true_masks`` (``heldout-channels ... masks=true``): the engine's exact masks at
    the frame's instant in place of the segmentation, at their own noise floor's edge term
    (0.01 px), as ``concealed.py --true-masks --edge-px 0.01``."""
    from torchfit.residuals import CHANNELS

    searched = None
    if blurred:
        settings = settings or SegmentationSettings(albedo_passes=1)
        _, _, problem, coverage, searched = _searched_coverage(folder, settings)
        video = dv.VideoProblem(problem, exposure=Exposure(0.5 if held_exposure is None else held_exposure, 0),
                                fit_exposure=held_exposure is None, coverage=coverage, robust=robust,
                                backcast=backcast)
    else:
        exact = {"edge_px": 0.01} if true_masks else {}  # exact masks: their own noise floor's edge term
        video = _video(folder, true_masks, robust=robust, backcast=backcast, **exact)
    base = video.fit((), None, searched)

    def value(model) -> dict:
        return {p: float(torch.as_tensor(v).reshape(-1)[0]) for p, v in model.values.get(effect, {}).items()}

    out = {}
    for label, fit in (("baseline", base), (effect, video.fit((effect,), base))):
        out[label] = {"heldout_noise_floors": fit.heldout_rms,
                      "nuisance_names": list(video.nuisance_names),
                      "edge_all_frames": [float(x) for x in fit.payload["model"].nuisances],
                      "value_all_frames": value(fit.payload["model"]),
                      "splits": [{"held_out": where, "heldout_noise_floors": rms,
                                  "edge_train_frames": [float(x) for x in model.nuisances],
                                  "value_train_frames": value(model),
                                  "channels": {c: {"rms": float(np.sqrt(np.nanmean((chans[c][held] / video.noise[c]) ** 2))),
                                                   "mean": float(np.nanmean(chans[c][held] / video.noise[c]))}
                                               for c in CHANNELS}}
                                 for where, rms, model, chans, (_, held)
                                 in zip(("end", "start"), fit.payload["heldout_split_rms"], fit.payload["held_models"],
                                        fit.payload["held_channels"], video.splits)]}
    return out


def heldout_swap(folder: Path, effect: str, backcast: bool = False) -> dict:
    """Whose frames turn a held-out test: the segmented video with the engine's true masks put in
    place of the segmentation on no frame, on the held-out frames, on the train frames, or on
    all; each time discover's baseline and its refit with ``effect`` (noise floors re-estimated
    from each mix, as discover does): held-out RMS in noise floors, the gain, the effect's value
    fitted on the train frames, and the edge bias there. The held-out part is the last quarter;
    with ``backcast`` (``heldout-swap ... backcast=true``) the first, the backcast's split, whose
    figures are given (the fits hold out both, as the default does where the blur is modelled)."""
    _, shape, camera = recording_parts(folder)
    observation, problem, span = load_problem(folder, shape, camera, False)
    split = 1 if backcast else 0
    held = span[dv.VideoProblem(problem, backcast=backcast).splits[split][1]]  # video frame numbers
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    out = {}
    for label, frames in (("segmented", []), ("true on held-out frames", held),
                          ("true on train frames", np.setdiff1d(span, held)), ("true", span)):
        masks = observation.masks.copy()
        masks[frames] = true[frames]
        video = dv.VideoProblem(problem_of(with_masks(observation, masks), shape, camera)[0], backcast=backcast)
        base = video.fit((), None)
        refit = video.fit((effect,), base)
        before, after = (fit.payload["heldout_split_rms"][split] for fit in (base, refit))
        out[label] = {"heldout_before": before, "heldout_after": after, "gain": 1.0 - after / before,
                      "train_value": {p: float(torch.as_tensor(v).reshape(-1)[0])
                                      for p, v in refit.payload["held_models"][split].values[effect].items()},
                      "train_edge_px": [float(x) for x in refit.payload["held_models"][split].nuisances],
                      "baseline_train_edge_px": [float(x) for x in base.payload["held_models"][split].nuisances]}
        print(label, json.dumps(out[label]), flush=True)
    return out


def _slow(values: np.ndarray, window: int = 7) -> np.ndarray:
    """(T - window + 1,) moving average of (T,) per-frame values: their slow part."""
    return np.convolve(values, np.ones(window) / window, mode="valid")


def chroma(weights: list[str]) -> dict:
    """Segmented against true masks in all three concealed sets, at each chroma weight
    (``SegmentationSettings.chroma_weight``), each recording's :func:`_error_row`, and their means.
    A constant edge bias is the edge nuisance's, so its mean is only listed, not averaged."""
    import torchfit.video as video

    out = {}
    for folder in _set_folders(("recordings", "recordings_fresh1", "recordings_fresh2")):
        frames, _ = video._read_video(folder / "video.mp4", 0, None)
        true = np.load(folder / "masks.npz")["masks"].astype(bool)
        for weight in weights:
            masks = video._segment(frames, video.SegmentationSettings(chroma_weight=float(weight)))["masks"]
            row = _error_row(masks, true)
            out.setdefault(f"{folder.parent.name}/{folder.name}", {})[weight] = row
            print(folder.parent.name, folder.name, weight, " ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
    out["mean"] = _means(list(out.values()), weights)
    return out


def _segmented_and_true(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W) bool: a recording's video segmented with the default settings, and its true masks."""
    import torchfit.video as video

    frames, _ = video._read_video(folder / "video.mp4", 0, None)
    return (video._segment(frames, video.SegmentationSettings())["masks"],
            np.load(folder / "masks.npz")["masks"].astype(bool))


def _set_folders(sets) -> list[Path]:
    """The recordings (folders with a truth.json) of the concealed ``sets`` beside this file."""
    return sorted(p for name in sets for p in (HERE / name).iterdir() if (p / "truth.json").exists())


def sets(names: list[str]) -> dict:
    """Is one set's segmentation worse than another's? Each recording of the sets ``names``
    segmented with the default settings against its true masks (:func:`_error_row`), and the
    means per set."""
    out: dict = {}
    for folder in _set_folders(names):
        row = _error_row(*_segmented_and_true(folder))
        out.setdefault(folder.parent.name, {})[folder.name] = row
        print(folder.parent.name, folder.name, " ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
    for name, rows in list(out.items()):
        out[name]["mean"] = _means([{"default": r} for r in rows.values()], ["default"])["default"]
    return out


def lens_masks(folder: Path) -> dict:
    """Are a lens recording's true masks where its mesh projects through the same lens? The masks
    against make_recordings' own rasteriser (the mesh cut into <= 5 mm triangles, each vertex
    distorted) at the true poses: centroid error RMS and mean (px), and the edge bias's mean (px)."""
    import make_recordings as mr
    import trimesh

    truth = json.loads((folder / "truth.json").read_text())
    masks = np.load(folder / "masks.npz")["masks"].astype(bool)
    cam = json.loads((folder / "camera.json").read_text())
    lens = truth["effects"].get("lens_distortion", {})
    distortion = (lens["k1"], lens["k2"]) if lens else None
    mesh = trimesh.load(folder / "mesh.obj", process=False)
    vertices, faces = (trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.005) if distortion
                       else (mesh.vertices, mesh.faces))
    drawn = np.stack([mr.render_silhouette(np.asarray(vertices), np.asarray(faces), np.asarray(R), np.asarray(t),
                                           cam, distortion=distortion)
                      for R, t in zip(truth["per_frame"]["R"], truth["per_frame"]["position"])])
    dx, dy, edge = frame_errors(drawn, masks)
    return {"c_rms": float(np.sqrt(np.mean(dx**2 + dy**2))), "c_mean": [float(dx.mean()), float(dy.mean())],
            "edge_mean": float(edge.mean()), "frames": len(masks)}


SOURCES = {"as recorded": {}, "no codec": {"codec": "h264rgb", "crf": 0}, "no sensor noise": {"noise_sigma": 0.0},
           "no motion blur": {"blur_subframes": 1},
           "motion blur alone": {"codec": "h264rgb", "crf": 0, "noise_sigma": 0.0},
           "none of them": {"codec": "h264rgb", "crf": 0, "noise_sigma": 0.0, "blur_subframes": 1}}


def _error_row(masks: np.ndarray, true: np.ndarray) -> dict:
    """(T, H, W) bool segmented against true masks: centroid error RMS over the frames (px) and of
    its 7-frame moving average less its mean (``c_slow``: the error that follows the scene, which
    the criterion's AR(1) noise does not expect), the edge bias's mean and spread and that of its
    moving average."""
    dx, dy, edge = frame_errors(masks, true)
    return {"c_rms": float(np.sqrt(np.mean(dx**2 + dy**2))),
            "c_slow": float(np.sqrt(np.mean(_slow(dx - dx.mean())**2 + _slow(dy - dy.mean())**2))),
            "edge_mean": float(edge.mean()), "edge_sd": float(edge.std()), "edge_slow": float(_slow(edge).std())}


ERROR_KEYS = ("c_rms", "c_slow", "edge_sd", "edge_slow")


def _means(rows: list[dict], columns, keys=ERROR_KEYS) -> dict:
    """Per column (a chroma weight, a source) the mean over ``rows`` (each ``{column: _error_row}``)
    of each of ``keys``: by default each error but the edge bias's mean, which the edge nuisance
    takes up."""
    return {c: {k: float(np.mean([r[c][k] for r in rows])) for k in keys} for c in columns}


def _remade(fresh: int, names: list[str], changes: dict, row) -> dict:
    """Each concealed recording of set ``fresh`` remade (same throw, scene and seeds, in a temporary
    folder) with each ``{label: RecordingSpec changes}``, and ``row(spec, folder)`` of each remake
    (a dict of figures)."""
    import tempfile

    import make_concealed as mc
    import make_recordings as mr

    mr.offscreen_gl()
    specs = {s.name: s for s, _ in mc.concealed_specs(fresh)}
    out = {}
    for name in names:
        for label, change in changes.items():
            with tempfile.TemporaryDirectory() as tmp:
                spec = specs[name].replace(**change)
                mr.make_recording(spec, Path(tmp), verbose=False)
                figures = row(spec, Path(tmp) / name)
            out.setdefault(f"{mc.fresh_folder(fresh).name}/{name}", {})[label] = figures
            print(fresh, name, label, " ".join(f"{k} {v:.3f}" for k, v in figures.items() if isinstance(v, float)),
                  flush=True)
    return out


def _segmentation_row(spec, folder: Path) -> dict:
    """A remake segmented with the default settings against its true masks (:func:`_error_row`)."""
    return _error_row(*_segmented_and_true(folder))


def _codec_row(spec, folder: Path) -> dict:
    """:func:`_segmentation_row` and the video's size in bits per pixel."""
    pixels = spec.width * spec.height * spec.n_frames
    return _segmentation_row(spec, folder) | {"bits_per_pixel": 8 * (folder / "video.mp4").stat().st_size / pixels}


def sources(fresh: int, names: list[str]) -> dict:
    """Which part of the recording makes the segmentation err: each concealed recording remade
    without H.264 (lossless RGB instead: libx264rgb, crf 0), without sensor noise, without motion
    blur (one render per frame at the frame's time), with motion blur alone (neither codec nor
    noise) and without all three (:func:`_remade`), and segmented (:func:`_segmentation_row`)."""
    return _remade(fresh, names, SOURCES, _segmentation_row)


def _regions_row(spec, folder: Path) -> dict:
    """A remake's :func:`regions` with the albedo pass (the default's segmentation), flat: each
    region's centroid RMS per axis, and the ramp's with independent signs."""
    result = regions(folder, SegmentationSettings(albedo_passes=1))
    row = {f"{part}_{axis}": result[part][f"centroid_{axis}"]["rms"]
           for part in ("interior", "ramp", "outside", "total") for axis in ("x", "y")}
    return row | {"ramp_if_independent": result["ramp"]["centroid_if_independent"],
                  "ramp_pixel_error_abs": result["ramp"]["pixel_error_abs"]}


def regions_sources(fresh: int, names: list[str]) -> dict:
    """:func:`regions` on each concealed recording remade without each source of error
    (:data:`SOURCES`, as :func:`sources`)."""
    return _remade(fresh, names, SOURCES, _regions_row)


# The H.264 encoding's two losses apart, and its quality: libx264 at crf 0 on yuv420p is lossless but
# for the colour's half resolution (4:2:0); yuv444p at crf 14 keeps full-resolution colour and
# quantises as the recordings do.
CODECS = {"as recorded (crf 14, 4:2:0)": {}, "4:2:0 alone (crf 0)": {"crf": 0},
          "quantisation alone (crf 14, 4:4:4)": {"codec": "h264_444"},
          "no codec": SOURCES["no codec"], **{f"crf {c}": {"crf": c} for c in (4, 8, 20, 26)}}


def codec(fresh: int, names: list[str]) -> dict:
    """Which part of the H.264 encoding makes the segmentation err, and how its quality does: each
    recording remade with the encodings of :data:`CODECS` (:func:`_remade`, :func:`_codec_row`)."""
    return _remade(fresh, names, CODECS, _codec_row)


def _stats(values: np.ndarray) -> dict:
    """Mean, spread about it, frame-to-frame jitter (second differences / sqrt 6) and the spread of
    the 7-frame moving average (the slow part) of (T,) per-frame values."""
    centred = values - values.mean()
    return {"mean": float(values.mean()), "rms": float(centred.std()),
            "jitter": float(np.std(np.diff(values, 2)) / np.sqrt(6)), "slow": float(_slow(centred).std())}


def _subframe_poses(truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """(T, K, 3) positions and (T, K, 3, 3) rotations at a recording's K blur sub-frames (centred
    on each frame over ``exposure_frac`` of the frame interval, as make_recordings.sample_times
    places them), splined from truth.json's per-frame poses. The first and last frames'
    sub-frames lie outside the frame times: the cubic extrapolates, the rotation spline cannot,
    so the end frames' rotations are the nearest (clipped) ones."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, RotationSpline

    per_frame = truth["per_frame"]
    times, sub_times = subframe_times(truth)
    position = CubicSpline(times, np.array(per_frame["position"]))(sub_times)
    rotation = RotationSpline(times, Rotation.from_matrix(np.array(per_frame["R"])))(
        np.clip(sub_times, times[0], times[-1]).ravel()).as_matrix().reshape(*sub_times.shape, 3, 3)
    return position, rotation


def _whole(masks: np.ndarray) -> np.ndarray:
    """(T,) bool: the (T, H, W) masks that are non-empty and clear of the image border."""
    return np.array([m.any() and not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
                     for m in masks])


def _exact_moments(truth: dict, shape, camera) -> tuple[tuple, torch.Tensor]:
    """The true silhouette's exact moments: at each frame's time ((area, centroid, covariance),
    :func:`torchfit.render.silhouette_moments`) and the (T, 6) raw moments averaged over the
    recording's blur sub-frames (:func:`_subframe_poses`). Pinhole only."""
    from torchfit.render import RenderMesh, silhouette_moments

    if camera.distorted:
        raise SystemExit("a lens recording: the exact moments here take no distortion")
    per_frame = truth["per_frame"]
    sub_position, sub_rotation = _subframe_poses(truth)
    frames, subframes = sub_position.shape[:2]
    mesh = RenderMesh.from_shape(shape, torch.float64)
    with torch.no_grad():
        mid = silhouette_moments(mesh, camera, torch.as_tensor(np.array(per_frame["R"])),
                                 torch.as_tensor(np.array(per_frame["position"])))
        subs = silhouette_moments(mesh, camera, torch.as_tensor(sub_rotation.reshape(-1, 3, 3)),
                                  torch.as_tensor(sub_position.reshape(-1, 3)))
    return mid, raw_from_central(*subs).reshape(frames, subframes, 6).mean(1)


def blur(folder: Path, near_px: str = "4", settings=None) -> dict:
    """Is the soft coverage a better observation once the model blurs too? The five channels of
    the segmented mask and of its soft coverage (the per-pixel estimate before smoothing and
    threshold, clipped to [0, 1], within ``near_px`` of the mask) against the exact moments of the
    true silhouette at the frame's time (``mid``) and against the average of its raw moments over
    the exposure (``exposure``: the recordings' own sub-frames, poses splined as in
    motion_blur.py). Moments are linear in coverage, so the blurred frame's coverage has exactly
    the exposure average's moments; the 0.5 contour of a blurred silhouette has not. Per pair and
    channel: :func:`_stats` over the frames where the mask is whole. ``settings``: the
    segmentation's (default: the defaults)."""
    from scipy import ndimage

    from torchfit.losses import central_moments, mask_moments
    from torchfit.residuals import channel_values

    truth, shape, camera = recording_parts(folder)
    mid, averaged = _exact_moments(truth, shape, camera)
    averaged = central_moments(averaged)
    masks, kept, true = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    whole = _whole(masks)
    near = np.stack([ndimage.binary_dilation(m, iterations=int(near_px)) for m in masks])
    observed = {"true mask": true, "mask": masks, "coverage": np.clip(np.stack(kept), 0, 1) * near}
    fitted = {"mid": mid, "exposure": averaged}
    out = {"frames": int(whole.sum())}
    for label, obs in observed.items():
        moments = mask_moments(torch.as_tensor(obs, dtype=torch.float64))
        for kind, model in fitted.items():
            values = channel_values(moments, model)
            out[f"{label} - {kind}"] = {k: _stats(v.numpy()[whole]) for k, v in values.items()}
    return out


def _stretch_row(masks: np.ndarray, folder: Path) -> dict:
    """:func:`torchfit.discover_video.motion_stretch` of (T, H, W) bool masks of the recording in
    ``folder`` against its true silhouettes at the frame times (exact moments at the true poses)."""
    from torchfit.discover_video import blur_named, motion_stretch
    from torchfit.losses import mask_moments
    from torchfit.render import RenderMesh, silhouette_moments
    from torchfit.residuals import channel_values

    truth, shape, camera = recording_parts(folder)
    per_frame = truth["per_frame"]
    mesh = RenderMesh.from_shape(shape, torch.float64)
    with torch.no_grad():
        fitted = silhouette_moments(mesh, camera, torch.as_tensor(np.array(per_frame["R"])),
                                    torch.as_tensor(np.array(per_frame["position"])))
    observed = mask_moments(torch.as_tensor(masks, dtype=torch.float64))
    whole = _whole(masks)
    result = motion_stretch(observed[2].numpy(), fitted[1].numpy(), fitted[2].numpy(),
                            np.array(per_frame["time"]), whole)
    speed = result["speed_px_per_frame"][whole]
    shape = channel_values(observed, fitted)["shape"].numpy()[whole]
    shape_rms = float(np.sqrt(np.mean((shape - shape.mean()) ** 2)))  # the edge nuisance takes the mean
    return {"mean": result["mean"], "correlation": result["correlation"], "shape_rms": shape_rms,
            "named": blur_named(result["mean"], result["correlation"], ["shape"], shape_rms),
            "speed_px_per_frame": [float(speed.min()), float(speed.max())], "frames": int(whole.sum())}


def stretch(folder: Path) -> dict:
    """The segmented masks' stretch along their own image motion against the true silhouettes,
    and its correlation with the speed squared (:func:`_stretch_row`): what the report's
    motion-blur line tests on the final model's silhouettes (``BLUR_CORRELATION``)."""
    masks, _, _ = segment_watching(folder, "_local_contrast", lambda result: None)
    return _stretch_row(masks, folder)


def stretch_sources(fresh: int, names: list[str]) -> dict:
    """Is the stretch motion blur? Each recording remade as recorded and without motion blur (one
    render per frame; codec and noise unchanged, as :func:`sources`), segmented, and
    :func:`_stretch_row` of each."""
    return _remade(fresh, names, {source: SOURCES[source] for source in ("as recorded", "no motion blur")},
                   lambda spec, folder: _stretch_row(_segmented_and_true(folder)[0], folder))

def _exact_coverage(mesh, camera, sub_rotation: np.ndarray, sub_position: np.ndarray,
                    x0: int, y0: int, h: int, w: int, samples: int = 4) -> np.ndarray:
    """(h, w) exact coverage of one frame's crop at ``(x0, y0)``: the true silhouette at each of its
    (K, 3, 3) ``sub_rotation`` and (K, 3) ``sub_position`` (:func:`_subframe_poses`) rendered hard at
    ``samples`` x ``samples`` a pixel, averaged over the sub-frames and each pixel's samples."""
    from torchfit.render import render_silhouettes

    window = torch.tensor([[x0 - 0.5 + 0.5 / samples, y0 - 0.5 + 0.5 / samples, 1.0 / samples]] * len(sub_position),
                          dtype=torch.float64)
    with torch.no_grad():
        hard = render_silhouettes(mesh, camera, torch.as_tensor(sub_rotation)[None], torch.as_tensor(sub_position)[None],
                                  window[None], size=(h * samples, w * samples), sigma=None)[0]
    return hard.mean(0).reshape(h, samples, w, samples).mean((1, 3)).numpy()


def ramp(fresh: int, name: str, source: str = "as recorded", settings: dict | None = None) -> dict:
    """Why a blurred ball comes out longer along its motion: the segmentation's per-pixel coverage
    (before smoothing and threshold) against the true coverage, the exposure's average of the
    silhouette at the recording's own sub-frames (poses splined from the truth, rendered hard at
    4 x 4 samples a pixel), on the blurred edge's ramp (true coverage 0.05-0.95) at the ends
    (within about 37 degrees of the motion, seen from the centroid) and at the sides (beyond 73
    degrees), over the faster half of the frames; and the mask's pixels there minus the true
    coverage's at or above 0.5. The recording is remade as ``source`` (:data:`SOURCES`) and
    segmented with the default settings changed by ``settings``."""
    import tempfile

    import make_concealed as mc
    import make_recordings as mr

    from torchfit.render import RenderMesh

    mr.offscreen_gl()
    spec = {s.name: s for s, _ in mc.concealed_specs(fresh)}[name].replace(**SOURCES[source])
    with tempfile.TemporaryDirectory() as tmp:
        mr.make_recording(spec, Path(tmp), verbose=False)
        folder = Path(tmp) / name
        truth, shape, camera = recording_parts(folder)
        masks, estimated, true = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage,
                                                  SegmentationSettings(**(settings or {})))
    sub_position, sub_rotation = _subframe_poses(truth)
    mesh = RenderMesh.from_shape(shape, torch.float64)
    frames = [t for t in range(len(sub_position)) if true[t].any()]
    crops = []
    for t in frames:
        rows, cols = np.nonzero(true[t])
        y0, x0 = rows.min() - 10, cols.min() - 10
        h, w = rows.max() + 11 - y0, cols.max() + 11 - x0
        cover = _exact_coverage(mesh, camera, sub_rotation[t], sub_position[t], x0, y0, h, w)
        v, u = np.mgrid[0:h, 0:w]
        centre = np.array([(cover * u).sum(), (cover * v).sum()]) / cover.sum()
        crops.append((cover, np.asarray(estimated[t])[y0:y0 + h, x0:x0 + w], masks[t][y0:y0 + h, x0:x0 + w],
                      np.stack((u - centre[0], v - centre[1]), -1), centre + (x0, y0)))
    centres = np.array([c[4] for c in crops])
    velocity = np.gradient(centres, np.array(frames), axis=0)
    speed = np.linalg.norm(velocity, axis=1)
    parts = {"ends": [], "sides": []}
    for (cover, est, mask, offset, _), v, s in zip(crops, velocity, speed):
        if s < np.median(speed):
            continue
        cos = np.abs(offset @ (v / s)) / (np.linalg.norm(offset, axis=-1) + 1e-9)
        on_ramp = (cover > 0.05) & (cover < 0.95)
        for part, where in (("ends", cos > 0.8), ("sides", cos < 0.3)):
            parts[part].append((float(np.mean(est[on_ramp & where] - cover[on_ramp & where])),
                                int(np.sum(mask & where)) - int(np.sum((cover >= 0.5) & where))))
    return {part: {"coverage_bias": float(np.mean([r[0] for r in rows])),
                   "extra_mask_pixels_per_frame": float(np.mean([r[1] for r in rows])), "frames": len(rows)}
            for part, rows in parts.items()}

def clip(folder: Path) -> dict:
    """What motion blur does to a ball's 0.5 contour, by geometry alone. A convex silhouette moved
    along a line during the exposure covers a point for the share of the exposure that the point's
    chord along the motion overlaps the swept interval; where the chord is at least half the
    travel ``L`` that share reaches 0.5 exactly at the chord's ends, elsewhere never. So a
    continuously blurred frame's 0.5 contour is the sharp silhouette less the two slivers where its
    chord is shorter than ``L / 2``: for a disc of radius ``r`` the band ``|y| <= sqrt(r^2 - L^2 /
    16)`` across the motion (checked on a 0.02 px grid, r 10, L 10.6: 311.63 px² against 311.62; the
    recordings' 5 sub-frames, 3 of 5 inside, lose a little more where the chord is under 3 L / 4:
    309.32). Per frame, from the true masks' radius (area) and centroid speed (``L`` = the
    exposure's share of it), the change in the ``scale`` channel (square root of area) that the
    frame-time render misses; a ball only."""
    truth = json.loads((folder / "truth.json").read_text())
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    radius = np.sqrt(true.sum((1, 2)) / np.pi)
    centre = np.array([np.argwhere(m).mean(0)[::-1] for m in true])
    travel = float(truth["render"]["exposure_frac"]) * np.linalg.norm(np.gradient(centre, axis=0), axis=1)
    y0 = radius * np.sqrt(np.clip(1 - travel**2 / (16 * radius**2), 0, 1))
    kept = 2 * (y0 * np.sqrt(radius**2 - y0**2) + radius**2 * np.arcsin(y0 / radius)) / (np.pi * radius**2)
    change = np.sqrt(kept) - 1
    return {"radius_px": [float(radius.min()), float(radius.max())], "travel_px": [float(travel.min()), float(travel.max())],
            "scale_change": [float(change.min()), float(change.max())], "per_frame_scale_change": change.tolist()}


def contrast(folder: Path) -> dict:
    """Does the outline's object-background contrast flag the frames the segmentation gets wrong?
    Per frame the contrast |F - B| (grey levels, the segmentation's own local shading fit) along the
    true outline, summarised four ways (median, 10th percentile, share of outline pixels below 20
    and below 30), and the correlation over the frames of the centroid error (distance from the
    median error, px) with the inverse median, the inverse 10th percentile and the two shares."""
    from edge_bias import outline

    masks, contrasts, true = segment_watching(folder, "_local_contrast",
                                              lambda result: np.linalg.norm(result[0], axis=-1))
    dx, dy, _ = frame_errors(masks, true)
    error = np.hypot(dx - np.median(dx), dy - np.median(dy))
    rows = np.array([[np.median(v), np.percentile(v, 10), np.mean(v < 20), np.mean(v < 30)]
                     for v in (contrasts[t][outline(true[t:t + 1])[0]] for t in range(len(true)))])
    predictors = {"inverse_median": 1 / rows[:, 0], "inverse_p10": 1 / np.maximum(rows[:, 1], 1.0),
                  "share_below_20": rows[:, 2], "share_below_30": rows[:, 3]}
    return {name: float(np.corrcoef(error, value)[0, 1]) for name, value in predictors.items()}


def _rotation_errors(cands, shape, truth: dict) -> torch.Tensor:
    """(B,) degrees between each candidate's orientation at t = 0 and the true one, modulo the
    shape's symmetries (:func:`torchfit.rotation.rotation_angle`, as the fit's report scores it)."""
    rot = quat_to_matrix(cands.quat().double())[:, None] @ torch.as_tensor(shape.symmetries, dtype=torch.float64)
    return torch.rad2deg(rotation_angle(torch.tensor(truth["params"]["R"], dtype=torch.float64), rot)).min(1).values


def search(folder: Path, settings=None) -> dict:
    """torchfit's search on the default segmentation's masks and on those of ``settings``: per
    stage the best loss and the candidate nearest the true orientation (its rotation error, rank
    and loss); then each search's best candidate scored on both masks (the polish's render, all
    frames). A search that lost the true basin ends with a loss above the other's best on its own masks."""
    truth, shape, camera = recording_parts(folder)
    problems = {label: load_problem(folder, shape, camera, False, given)[1]
                for label, given in (("default", None), ("changed", settings))}
    knobs, out = SearchSettings(), {}
    for label, problem in problems.items():
        stages = []

        def snapshot(stage, cands, losses, stages=stages):
            errors = _rotation_errors(cands, shape, truth)
            near = int(torch.argmin(errors))
            stages.append({"stage": stage, "candidates": len(cands), "best_loss": float(losses[0]),
                           "best_rotation_deg": float(errors[0]), "nearest_rotation_deg": float(errors[near]),
                           "nearest_rank": near, "nearest_loss": float(losses[near])})
        result = search_fit(problem, knobs, snapshot=snapshot)
        best = result.candidates.select(torch.zeros(1, dtype=torch.long))
        with torch.no_grad():
            scored = {masks: float(candidate_losses(other, best, len(other.times), knobs.polish_crop,
                                                    knobs.polish_sigma)[0]) for masks, other in problems.items()}
        out[label] = {"stages": stages, "rotation_deg": float(_rotation_errors(best, shape, truth)[0]),
                      "loss_on": scored}
    return out


EXPOSURE_GRID = (0.0, 0.25, 0.5, 0.75, 1.0)


def _searched_coverage(folder: Path, settings=None) -> tuple[dict, object, object, torch.Tensor, object]:
    """A recording segmented with ``settings``: its truth, shape, problem, the (T, 6) raw moments
    of its soft coverage over the fitted span, and torchfit's search on it (default settings)."""
    truth, shape, camera = recording_parts(folder)
    observation, problem, span = load_problem(folder, shape, camera, False, settings)
    coverage = torch.as_tensor(observation.coverage_moments[span])
    return truth, shape, problem, coverage, search_fit(problem, SearchSettings())


def exposure(folder: Path, settings=None, fractions: tuple[float, ...] = EXPOSURE_GRID) -> dict:
    """Could the exposure be read from the video? The baseline (one search, then discover's
    refit) with the soft coverage compared with the silhouette averaged over each of
    ``fractions`` (default ``EXPOSURE_GRID``; the recording's own sub-frame count): per fraction
    the RMS of each residual channel over the used frames (outliers left out; px for the
    centroid, relative for the others) and the fit's chi-squared per observation against its own
    noise floors."""
    truth, _, problem, coverage, searched = _searched_coverage(folder, settings)
    own = recording_exposure(truth)
    rows = {}
    for fraction in fractions:
        video = dv.VideoProblem(problem, exposure=Exposure(fraction, own.taps), coverage=coverage)
        base = video.fit((), None, searched)
        used = video.problem.used.cpu().numpy().astype(bool)
        used[video.outliers] = False
        rows[f"{fraction:g}"] = {
            "rms": {name: float(np.sqrt(np.nanmean(values[used] ** 2))) for name, values in base.payload["channels"].items()},
            "chi2_per_obs": base.rss / base.n_obs, "noise": video.noise, "edge_px": list(base.payload["model"].nuisances)}
    return {"true_exposure": own.fraction, "taps": own.taps, "fractions": rows}


def _along_motion_fraction(observed: np.ndarray, reference: np.ndarray, velocity: np.ndarray, used: np.ndarray,
                           end_weight: float) -> float:
    """The exposure fraction ``e`` that the extra variance along the motion of ``observed`` over
    ``reference`` ((T, 6) raw moments) gives: a translation of ``v`` pixels per frame spreads a
    silhouette's centroid over the exposure with variance ``(w / 2) e^2 |v|^2`` along ``v`` (``w``
    :attr:`torchfit.search.Exposure.end_weight`), so ``e^2`` is the least-squares slope over the
    ``used`` frames of the excess variance along ``velocity`` ((T, 2) px/frame) on ``(w / 2) |v|^2``."""
    from torchfit.losses import central_moments

    def covariance(raw):
        return central_moments(torch.as_tensor(raw, dtype=torch.float64))[2].numpy()

    speed = np.linalg.norm(velocity, axis=1)
    along = velocity / np.maximum(speed, 1e-9)[:, None]
    excess = np.einsum("ti,tij,tj->t", along, covariance(observed) - covariance(reference), along)[used]
    basis = end_weight / 2 * speed[used] ** 2
    return float(np.sqrt(max((excess * basis).sum() / (basis * basis).sum(), 0.0)))


def _ramp_width(length: np.ndarray, sigma: float) -> np.ndarray:
    """``6 * integral F (1 - F)`` across an edge whose profile ``F`` is a ramp ``length`` px long
    ((N,)) smoothed by a Gaussian of ``sigma`` px: ``length`` for the ramp alone, ``3.39 sigma``
    for the Gaussian alone."""
    from scipy.special import ndtr

    def antiderivative(x):  # of the normal CDF
        return x * ndtr(x) + np.exp(-x * x / 2) / np.sqrt(2 * np.pi)

    z = np.linspace(-30.0, 30.0, 6001)[None]
    length = np.maximum(np.asarray(length, np.float64)[:, None], 1e-6)  # (N, 1)
    profile = sigma / length * (antiderivative((z + length / 2) / sigma) - antiderivative((z - length / 2) / sigma))
    return 6 * (profile * (1 - profile)).sum(-1) * (z[0, 1] - z[0, 0])


NEAR_PX = (2, 6, 8, 12)  # blur-estimate: other bands than the settings' coverage_near_px for the coverage's moments


def _quantile_bins(values: np.ndarray, bins: int) -> np.ndarray:
    """(N,) index 0..bins-1 of each of (N,) ``values`` among their ``bins`` quantiles, lowest first."""
    edges = np.quantile(values, np.linspace(0, 1, bins + 1))
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, bins - 1)


def _coverage_within(kept: list, masks: np.ndarray, band: int, clip: bool = True) -> np.ndarray:
    """(T, 6) raw moments of each frame's soft coverage (``kept``, (H, W) each) within ``band``
    4-neighbour steps of its mask, clipped to [0, 1] or not, as the segmentation keeps them."""
    from scipy import ndimage

    from torchfit.video import raw_moments

    return raw_moments(np.stack([(np.clip(c, 0.0, 1.0) if clip else c) * ndimage.binary_dilation(m, iterations=band)
                                 for c, m in zip(kept, masks)]))


def blur_estimate(folder: Path, settings=None, bins: int = 8) -> dict:
    """Can the exposure be read from the blur alone, without the fit? Two estimates from the
    segmentation, each against the recording's true fraction.

    ``moments``: :func:`_along_motion_fraction` (velocities from the true centroids) of four
    pairs: the exact exposure average of the true silhouette's moments over the exact moments at
    the frame's time (the relation itself), the segmented soft coverage (as cached, within
    ``coverage_near_px`` of the mask) over the exact frame-time moments, the coverage over the
    segmented mask (an estimate from the video alone), and the exact average over the mask; then
    the coverage counted within each of ``NEAR_PX`` (4-neighbour steps) of the mask over the exact
    frame-time moments, and the coverage without its clip to [0, 1] within 4 and each of
    ``NEAR_PX``. ``area``: each coverage's m00 over the exact average's, its mean, sd and drift
    (the slope of a line over the frames, end minus start) over the frames.

    ``ramp``: the coverage's edge ramp (video alone). Per pixel of the coverage between 0.02
    and 0.98 the edge's normal ``n`` is its gradient's; a ramp ``L`` long along the motion is
    ``L |n . u|`` long along the normal. Pixels binned (``bins`` quantiles) by ``|v| |n . u|``
    (``v`` the mask centroid's px per frame): per bin ``6 sum c (1 - c) / sum |grad c|``, the
    ramp's width (:func:`_ramp_width`), fitted over ``e`` (0.01 steps) and a Gaussian's ``sigma``."""
    from scipy import ndimage

    from torchfit.video import raw_moments

    truth, shape, camera = recording_parts(folder)
    own = recording_exposure(truth)
    mid, averaged = _exact_moments(truth, shape, camera)
    mid, averaged = raw_from_central(*mid).numpy(), averaged.numpy()
    masks, kept, _ = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    cover = _coverage_within(kept, masks, (settings or SegmentationSettings()).band_steps(*masks.shape[1:]))
    mask = raw_moments(masks)
    used = _whole(masks)
    used[[0, -1]] = False
    velocity = np.gradient(mid[:, 1:3] / mid[:, :1], axis=0)
    w = own.end_weight
    pairs = {"exact average / exact": (averaged, mid), "coverage / exact": (cover, mid),
             "coverage / mask": (cover, mask), "exact average / mask": (averaged, mask)}
    pairs |= {f"coverage within {near} px / exact": (_coverage_within(kept, masks, near), mid) for near in NEAR_PX}
    pairs |= {f"unclipped coverage within {near} px / exact": (_coverage_within(kept, masks, near, False), mid)
              for near in (4, *NEAR_PX)}
    moments = {k: _along_motion_fraction(a, b, velocity, used, w) for k, (a, b) in pairs.items()}
    area = {}  # the coverage's m00 over the exact average's: mean, sd and drift (end minus start of a line) over frames
    for k, (a, _) in pairs.items():
        if k.startswith(("coverage", "unclipped")) and k.endswith(" / exact"):
            ratio, frame = a[used, 0] / averaged[used, 0], np.flatnonzero(used)
            drift = np.polyfit((frame - frame.min()) / max(frame.max() - frame.min(), 1), ratio, 1)[0]
            area[k.removesuffix(" / exact")] = [float(ratio.mean()), float(ratio.std()), float(drift)]

    motion = mask_velocity(masks)
    x, ramp, grad = [], [], []
    for t in np.flatnonzero(used):
        c = np.clip(kept[t], 0.0, 1.0) * ndimage.binary_dilation(masks[t], iterations=6)
        gy, gx = np.gradient(c)
        g = np.hypot(gx, gy)
        edge = (c > 0.02) & (c < 0.98) & (g > 0)
        x.append(np.abs(gx[edge] * motion[t, 0] + gy[edge] * motion[t, 1]) / g[edge])
        ramp.append((c * (1 - c))[edge])
        grad.append(g[edge])
    x, ramp, grad = map(np.concatenate, (x, ramp, grad))
    which = _quantile_bins(x, bins)
    travel = np.array([np.average(x[which == b], weights=grad[which == b]) for b in range(bins)])
    width = np.array([6 * ramp[which == b].sum() / grad[which == b].sum() for b in range(bins)])
    lengths = np.linspace(0.0, 1.05 * travel.max(), 211)
    tables = {float(sigma): _ramp_width(lengths, sigma) for sigma in np.linspace(0.2, 4.0, 39)}
    fits = [(float(np.sqrt(np.mean((np.interp(e * travel, lengths, table) - width) ** 2))), float(e), sigma)
            for e in np.linspace(0.0, 1.0, 101) for sigma, table in tables.items()]
    rms, fraction, sigma = min(fits)
    return {"true_exposure": own.fraction, "frames": int(used.sum()), "moments": moments, "area": area,
            "ramp": {"fraction": fraction, "sigma_px": sigma, "rms_px": rms,
                     "travel_px": travel.tolist(), "width_px": width.tolist()}}


SPEED_BANDS = (("steps", 4), ("steps", 6), ("steps", 8), ("px", 4), ("px", 6), ("px", 8), ("px", 12),
               ("px past half the travel", 2), ("px past half the travel", 3),
               ("steps and half the travel along it", 4))  # blur-speed


def _band(mask: np.ndarray, kind: str, width: int, velocity: np.ndarray = np.zeros(2)) -> np.ndarray:
    """(H, W) bool: the pixels within ``width`` of ``mask`` ((H, W) bool), counted in 4-neighbour
    ``steps`` (as the segmentation's ``coverage_near_px``), in Euclidean ``px``, in Euclidean
    ``px past half the travel``: ``width`` px beyond half the frame's travel (the norm of
    ``velocity``, (2,) px per frame), as far as the blur of any exposure up to the whole frame
    interval reaches, or ``steps and half the travel along it``: the band of ``width`` steps swept
    half the travel either way along the motion (:func:`torchfit.video.motion_band`)."""
    from scipy import ndimage

    from torchfit.video import motion_band

    if kind == "steps":
        return ndimage.binary_dilation(mask, iterations=width)
    if kind == "steps and half the travel along it":
        return motion_band(mask, width, velocity)
    reach = width + (float(np.linalg.norm(velocity)) / 2 if kind == "px past half the travel" else 0.0)
    return ndimage.distance_transform_edt(~mask) <= reach


def blur_speed(folder: Path, settings=None, bins: int = 4) -> dict:
    """Does the coverage read the blur at a fraction that depends on the speed? Per frame, the
    soft coverage's variance along the motion minus the exact exposure average's
    (:func:`_exact_moments`; px^2; velocity from the exact frame-time centroids), with the
    coverage counted within each band of ``SPEED_BANDS`` (4-neighbour steps or Euclidean px of
    the mask, or px past half the mask centroid's travel in the frame: the video alone), clipped
    to [0, 1] and not. Frames are binned by speed (``bins`` quantiles); per bin the mean excess
    along and across the motion, the blur's half-length ``e |v| / 2`` (px, the recording's
    exposure ``e``) and the area ratio. ``slope``: the excess along the
    motion regressed on ``|v|^2`` (with a constant), px^2 per (px/frame)^2; a band that reads
    the blur at the true fraction has slope 0."""
    from torchfit.losses import central_moments
    from torchfit.video import raw_moments

    truth, shape, camera = recording_parts(folder)
    own = recording_exposure(truth)
    mid, averaged = _exact_moments(truth, shape, camera)
    mid, averaged = raw_from_central(*mid).numpy(), averaged.numpy()
    masks, kept, _ = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    used = _whole(masks)
    used[[0, -1]] = False
    velocity = np.gradient(mid[:, 1:3] / mid[:, :1], axis=0)[used]
    speed = np.linalg.norm(velocity, axis=1)
    along = velocity / np.maximum(speed, 1e-9)[:, None]
    across = np.stack((-along[:, 1], along[:, 0]), 1)

    def covariance(raw):
        return central_moments(torch.as_tensor(raw, dtype=torch.float64))[2].numpy()[used]

    reference = covariance(averaged)
    which = _quantile_bins(speed, bins)
    out = {"true_exposure": own.fraction, "frames": int(used.sum()),
           "speed_px_per_frame": [float(speed[which == b].mean()) for b in range(bins)],
           "half_blur_px": [float(own.fraction * speed[which == b].mean() / 2) for b in range(bins)], "bands": {}}
    design = np.stack((np.ones_like(speed), speed**2), 1)
    travel = np.nan_to_num(mask_velocity(masks))  # (T, 2) px per frame, the video's
    for clip in (True, False):
        for kind, width in SPEED_BANDS:
            raw = raw_moments(np.stack([(np.clip(c, 0.0, 1.0) if clip else c) * _band(m, kind, width, v)
                                        for c, m, v in zip(kept, masks, travel)]))
            excess = covariance(raw) - reference
            on = np.einsum("ti,tij,tj->t", along, excess, along)
            off = np.einsum("ti,tij,tj->t", across, excess, across)
            ratio = raw[used, 0] / averaged[used, 0]
            out["bands"][f"{'clipped' if clip else 'unclipped'} within {width} {kind}"] = {
                "along_px2": [float(on[which == b].mean()) for b in range(bins)],
                "across_px2": [float(off[which == b].mean()) for b in range(bins)],
                "area_ratio": [float(ratio[which == b].mean()) for b in range(bins)],
                "slope": [float(v) for v in np.linalg.lstsq(design, on, rcond=None)[0]]}
    return out


def shape_frames(folder: Path, settings=None) -> dict:
    """Frame by frame, the soft coverage (``settings``) against the true silhouette's exact
    exposure average (:func:`_exact_moments`): the mask centroid's speed (px per frame), the
    area ratio and the variance's excess along and across the motion (px^2)."""
    from torchfit.losses import central_moments

    truth, shape, camera = recording_parts(folder)
    observation, _, _ = load_problem(folder, shape, camera, False, settings)
    _, averaged = _exact_moments(truth, shape, camera)
    area_o, _, cov_o = central_moments(torch.as_tensor(observation.coverage_moments))
    area_e, _, cov_e = central_moments(averaged)
    velocity = np.nan_to_num(mask_velocity(observation.masks))
    rows = []
    for t in np.flatnonzero(area_o.numpy() > 0):
        speed = float(np.linalg.norm(velocity[t]))
        along = velocity[t] / max(speed, 1e-9)
        across = np.array([-along[1], along[0]])
        extra = (cov_o[t] - cov_e[t]).numpy()
        rows.append({"frame": int(t), "speed_px": speed, "area_ratio": float(area_o[t] / area_e[t]),
                     "along_px2": float(along @ extra @ along), "across_px2": float(across @ extra @ across)})
        print(" ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    return {"frames": rows}


AREA_BANDS = (2, 4, 6, 8, 12)  # area: the bands the coverage is counted within
LOW_CONTRAST = 50.0  # area: grey levels of object minus background below which a frame counts as low-contrast


def area(folder: Path, settings=None) -> dict:
    """The soft coverage's area (m00) over the true silhouette's exact exposure average, frame by
    frame, against the contrast between object and background there: the video's median
    background over a ring 3-6 px outside the true mask against the frame's pixels 3 px inside
    it (BGR distance, grey levels). Per band of ``AREA_BANDS``, clipped to [0, 1] and not: the
    ratio's mean over the high- and the low-contrast frames (``LOW_CONTRAST``), their difference,
    its correlation with the contrast and its sd over the used frames."""
    from scipy import ndimage

    from torchfit.video import _read_video

    truth, shape, camera = recording_parts(folder)
    _, averaged = _exact_moments(truth, shape, camera)
    averaged = averaged.numpy()
    masks, kept, true = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    used = _whole(masks)
    used[[0, -1]] = False
    frames, _ = _read_video(folder / "video.mp4", 0, None)
    background = np.median(frames, 0).astype(np.float64)
    contrast = np.full(len(frames), np.nan)
    for t in np.flatnonzero(used):
        ring = ndimage.binary_dilation(true[t], iterations=6) & ~ndimage.binary_dilation(true[t], iterations=2)
        inside = ndimage.binary_erosion(true[t], iterations=3)
        if ring.any() and inside.any():
            contrast[t] = np.linalg.norm(frames[t][inside].mean(0) - background[ring].mean(0))
    used &= np.isfinite(contrast)
    low, high = used & (contrast < LOW_CONTRAST), used & (contrast >= LOW_CONTRAST)
    rows = {}
    for clip in (True, False):
        for band in AREA_BANDS:
            ratio = _coverage_within(kept, masks, band, clip)[:, 0] / averaged[:, 0]
            row = {"high": float(ratio[high].mean()) if high.any() else None,
                   "low": float(ratio[low].mean()) if low.any() else None,
                   "corr_contrast": float(np.corrcoef(contrast[used], ratio[used])[0, 1]), "sd": float(ratio[used].std())}
            row["low_minus_high"] = row["low"] - row["high"] if low.any() and high.any() else None
            rows[f"{'clipped' if clip else 'unclipped'} within {band} px"] = row
    return {"frames": int(used.sum()), "low_contrast_frames": np.flatnonzero(low).tolist(),
            "contrast": [None if not np.isfinite(c) else float(c) for c in contrast], "area": rows}


COVERAGE_PARTS = ("area", "centroid", "shape")  # exact-coverage: the coverage's parts that can come from the truth
SHAPE_PARTS = ("spread", "stretch")  # exact-coverage: the shape's isotropic part and the rest, each alone


def mixed_moments(seen: np.ndarray, exact: np.ndarray, parts: tuple[str, ...]) -> np.ndarray:
    """(T, 6) raw moments with the ``parts`` (of ``COVERAGE_PARTS`` and ``SHAPE_PARTS``) of
    ``exact`` and the rest of ``seen`` (both (T, 6) raw moments about one origin); frames ``seen``
    leaves empty stay so. The shape's error (the covariance's, exact minus seen) splits into
    ``spread``, its isotropic part (half its trace times the identity), and ``stretch``, the rest
    (traceless: elongation and its axis); ``shape`` is both."""
    from torchfit.losses import central_moments

    seen_t = torch.as_tensor(seen, dtype=torch.float64)
    empty = seen_t[:, 0] <= 0
    unit = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 1.0], dtype=torch.float64)  # stands in for an empty frame
    own = central_moments(torch.where(empty[:, None], unit, seen_t))
    truth = central_moments(torch.as_tensor(exact, dtype=torch.float64))
    chosen = [e if name in parts else o for name, e, o in zip(COVERAGE_PARTS, truth, own)]
    if "shape" not in parts:
        error = truth[2] - own[2]  # (T, 2, 2)
        spread = error.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] * torch.eye(2, dtype=torch.float64)
        chosen[2] = own[2] + ("spread" in parts) * spread + ("stretch" in parts) * (error - spread)
    mixed = raw_from_central(*chosen).numpy()
    mixed[empty.numpy()] = np.asarray(seen)[empty.numpy()]
    return mixed


def exact_coverage(folder: Path, settings=None, parts: tuple[str, ...] = COVERAGE_PARTS) -> dict:
    """Discover with the recording's exposure (``concealed.py --exposure``) on a coverage whose
    ``parts`` come from the true silhouette's exact exposure average (:func:`_exact_moments`) and
    the rest from the segmentation (``settings``): ``area`` its m00, ``centroid`` its centre,
    ``shape`` its central second moments per unit area. The masks, and so the search and the
    edge nuisance's table, stay the segmentation's. Which of the coverage's errors turn a verdict?"""
    truth, shape, camera = recording_parts(folder)
    observation, problem, span = load_problem(folder, shape, camera, False, settings)
    _, averaged = _exact_moments(truth, shape, camera)
    mixed = mixed_moments(observation.coverage_moments, averaged.numpy(), parts)
    out = dv.discover_video(problem, replace(observation, coverage_moments=mixed), span, candidates=CANDIDATES,
                            settings=dv.VIDEO_SELECTION, truth=truth, overlay=False,
                            exposure=recording_exposure(truth))
    return {"parts": list(parts), "verdict": out["verdict"], "verdict_withheld": out.get("verdict_withheld"),
            "iou_final": out["iou_final"], "report": out["report"]}


def error_speed(folder: Path, settings=None, bins: int = 4) -> dict:
    """Does the segmentation err more on fast frames? Per residual channel
    (:data:`torchfit.residuals.CHANNELS`), the segmentation's error, its RMS about its median
    within each speed quartile (slowest first): the masks against the engine's true masks
    (``masks.npz``, at each frame's time), and the soft coverage (``settings``) against the true
    silhouette's exact exposure average (:func:`_exact_moments`). Speed: the exact frame-time
    centroid's, central differences, px per frame. ``ratio``: fastest over slowest quartile."""
    from torchfit.losses import central_moments, mask_moments
    from torchfit.residuals import CHANNELS, channel_values

    truth, shape, camera = recording_parts(folder)
    observation, _, span = load_problem(folder, shape, camera, False, settings)
    mid, averaged = _exact_moments(truth, shape, camera)
    speed = np.linalg.norm(np.gradient(mid[1].numpy(), axis=0), axis=1)[span]
    quartile = _quantile_bins(speed, bins)
    true = torch.as_tensor(np.load(folder / "masks.npz")["masks"][span], dtype=torch.float64)
    seen = torch.as_tensor(observation.masks[span], dtype=torch.float64)
    pairs = {"masks": (mask_moments(seen), mask_moments(true)),
             "coverage": (central_moments(torch.as_tensor(observation.coverage_moments[span], dtype=torch.float64)),
                          central_moments(torch.as_tensor(np.asarray(averaged)[span], dtype=torch.float64)))}
    whole = _whole(observation.masks[span])
    out = {"speed_px_per_frame": [float(speed[quartile == k].mean()) for k in range(bins)]}
    for kind, (observed, exact) in pairs.items():
        errors = channel_values(observed, exact)
        rows = {}
        for c in CHANNELS:
            v = errors[c].numpy()
            keep = whole & np.isfinite(v)
            v = v - np.median(v[keep])
            rms = [float(np.sqrt(np.mean(v[keep & (quartile == k)] ** 2))) for k in range(bins)]
            rows[c] = {"rms": rms, "ratio": rms[-1] / rms[0] if rms[0] > 0 else float("nan")}
        out[kind] = rows
    return out


def spread_stall(folder: Path, settings=None, priors=((1.0, 1.0), (0.0, math.inf)), more: int = 45) -> dict:
    """Does a fitted point spread leave the baseline short of its minimum? One search, then
    discover's baseline on the coverage (the recording's exposure, ``concealed.py --exposure``)
    without a point spread and with each of ``priors`` (``(mean, std)`` px², std infinite: none):
    its chi-squared per observation, its spread, and both after ``more`` Levenberg-Marquardt
    iterations from there (the baseline itself stops after 15)."""
    truth, _, problem, coverage, searched = _searched_coverage(folder, settings)
    rows = {}
    for prior in (None,) + tuple(priors):
        video = dv.VideoProblem(problem, exposure=recording_exposure(truth), coverage=coverage, point_spread=prior)
        base = video.fit((), None, searched)
        every = video.problem.used.cpu().numpy().astype(bool)
        model, resid, _ = video._lm(base.payload["model"], every, more)
        rows["none" if prior is None else f"{prior[0]:g} ± {prior[1]:g}"] = {
            "chi2_per_obs": base.rss / base.n_obs, "spread": video.nuisance(base.payload["model"].nuisances, "point_spread"),
            f"chi2_per_obs_after_{more}_more": video._cost(resid) / base.n_obs,
            f"spread_after_{more}_more": video.nuisance(model.nuisances, "point_spread")}
        print(folder.name, list(rows)[-1], json.dumps(rows[list(rows)[-1]]), flush=True)
    return rows


def baseline_starts(folder: Path, settings=None, starts: int = 4) -> dict:
    """Which of the search's distinct candidates does discover's baseline do best from? One
    search, then the baseline (the coverage against the recording's exposure, as ``concealed.py
    --exposure``; its noise floors from the search's best, as discover sets them) run by
    Levenberg-Marquardt from each of the first ``starts`` candidates: per candidate its search
    loss, its rotation error against the truth at t = 0 and the baseline's chi-squared per
    observation after discover's 15 iterations."""
    truth, shape, problem, coverage, searched = _searched_coverage(folder, settings)
    video = dv.VideoProblem(problem, exposure=recording_exposure(truth), coverage=coverage)
    models = video.search_starts(searched, starts)
    video._set_noise(models[0])  # the noise floors and the edge table from the best, as discover's fit sets them
    ended = video._lm_many(models, video.problem.used.cpu().numpy().astype(bool), video.iterations)
    n_obs = int(torch.isfinite(ended[0][1]).sum())  # the residuals and the edge bias's prior terms
    errors = _rotation_errors(searched.candidates, shape, truth)
    rows = [{"rank": k, "search_loss": float(searched.losses[k]), "rotation_deg": float(errors[k]),
             "chi2_per_obs": video._cost(resid) / n_obs,
             "rotation_after_deg": float(_rotation_errors(model.cands, shape, truth)[0])}
            for k, (model, resid, _) in enumerate(ended)]
    for row in rows:
        print(folder.name, json.dumps(row), flush=True)
    return {"baseline_chi2_per_obs": rows[0]["chi2_per_obs"], "starts": rows}


def _setting_value(text: str):
    """A ``SETTING=V`` argument's value: an integer, a number, true / false, or the word itself."""
    if text.lstrip("-").isdigit():
        return int(text)
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return float(text)
    except ValueError:
        return text


END_FRAMES = 5  # end-frames: the frames counted at each end of a clip


def _frame_noise(values: np.ndarray) -> float:
    """A channel's noise floor as discover measures it (:func:`torchfit.residuals.noise_floor`,
    second differences, lag-one correlation :data:`torchfit.discover_video.FRAME_CORRELATION`),
    on the finite frames of (T,) ``values``."""
    from torchfit.residuals import noise_floor

    return noise_floor(values[np.isfinite(values)], dv.FRAME_CORRELATION)


def _coverage_errors(folder: Path, settings: list[dict]) -> tuple[list[np.ndarray], np.ndarray]:
    """The recording ``folder``'s soft coverage against the true silhouette's exact exposure
    average (:func:`_exact_moments`), per segmentation (``settings``, each a
    :class:`SegmentationSettings`' changes): its (C, T) channel errors
    (:data:`torchfit.residuals.CHANNELS`; ``shape`` and ``orientation`` along the seen outline's
    long axis, as :func:`torchfit.residuals.channel_values` takes it without one). Also
    the exact centroid's (T,) speed, px per frame."""
    truth, shape, camera = recording_parts(folder)
    mid, averaged = _exact_moments(truth, shape, camera)
    out = [_channel_errors(load_observation(str(folder / "video.mp4"), camera=camera,
                                            settings=SegmentationSettings(**changes)), averaged)
           for changes in settings]
    return out, np.linalg.norm(np.gradient(mid[1].numpy(), axis=0), axis=1)


def _channel_errors(observation, averaged: torch.Tensor) -> np.ndarray:
    """(C, T) channel errors (:data:`torchfit.residuals.CHANNELS`) of ``observation``'s soft
    coverage against the (T, 6) raw moments ``averaged`` (:func:`_exact_moments`' second)."""
    from torchfit.losses import central_moments
    from torchfit.residuals import CHANNELS, channel_values

    exact = central_moments(torch.as_tensor(np.asarray(averaged), dtype=torch.float64))
    seen = central_moments(torch.as_tensor(observation.coverage_moments, dtype=torch.float64))
    values = channel_values(seen, exact)
    return np.stack([np.asarray(values[c], np.float64) for c in CHANNELS])


def _lag_one(values: np.ndarray) -> float:
    """The lag-one correlation of the noise on a (T,) channel, read from its first differences so
    that a smooth trend does not count: for AR(1) noise with correlation r the differences have a
    lag-one correlation of -(1 - r) / 2, so r = 1 + 2 x that. Over the finite frames, the
    differences about their median and clipped at 6 robust spreads (a failed frame's jump)."""
    step = np.diff(values[np.isfinite(values)])
    step = step - np.median(step)
    limit = 6.0 * 1.4826 * np.median(np.abs(step))
    step = np.clip(step, -limit, limit)
    return float(1.0 + 2.0 * (step[:-1] * step[1:]).sum() / (step * step).sum())


def frame_correlation(folders: list[Path]) -> dict:
    """How correlated the segmentation's error is from one frame to the next, the number discover's
    noise model holds at :data:`torchfit.discover_video.FRAME_CORRELATION`: on each set's controls
    (nothing hidden, no lens), the default segmentation's (albedo pass) coverage against the exact
    exposure average, per channel :func:`_lag_one`; per set the median over its controls."""
    from torchfit.residuals import CHANNELS

    result = {}
    for folder in folders:
        rows = {}
        for name in sorted(f.name for f in folder.iterdir() if f.name.startswith("control") and (f / "truth.json").exists()):
            (errors,), _ = _coverage_errors(folder / name, [{"albedo_passes": 1}])
            rows[name] = dict(zip(CHANNELS, (_lag_one(e) for e in errors)))
            print(folder.name, name, " ".join(f"{c} {v:+.2f}" for c, v in rows[name].items()), flush=True)
        result[folder.name] = {"recordings": rows,
                               "median": {c: float(np.median([r[c] for r in rows.values()])) for c in CHANNELS}}
        print(folder.name, "median", " ".join(f"{c} {v:+.2f}" for c, v in result[folder.name]["median"].items()), flush=True)
    return result


def end_frames(folder: Path, variants: list[dict]) -> dict:
    """Does the coverage err more on a clip's first and last frames? On every recording of the set
    ``folder`` without a lens, each channel's error (:data:`torchfit.residuals.CHANNELS`) of the
    soft coverage against the true silhouette's exact exposure average (:func:`_exact_moments`),
    about its median over the frames, squared in units of the default segmentation's noise
    floor (:func:`_frame_noise`; the default: the albedo pass), summed over the
    channels. Per segmentation (the default, then each of ``variants``, setting changes on top of
    it): the median over the recordings of that sum at frames 0..4, the middle frames' median and
    the last five frames, and each channel's noise floor over the default's (median over
    the recordings). ``speed``: the exact centroid's, px per frame, the same positions."""
    from torchfit.residuals import CHANNELS

    k = END_FRAMES
    settings = [{"albedo_passes": 1}] + [{"albedo_passes": 1} | v for v in variants]
    names = [f.name for f in sorted(folder.iterdir()) if (f / "truth.json").exists() and not f.name.startswith("lens")]
    errors = [[] for _ in settings]  # per segmentation, per recording: (C, T) errors
    speeds = []
    for name in names:
        found, speed = _coverage_errors(folder / name, settings)
        speeds.append(speed)
        for out, one in zip(errors, found):
            out.append(one)
        print(folder.name, name, flush=True)

    def ends(series: np.ndarray) -> list[float]:
        return [*series[:k], float(np.nanmedian(series[k:-k])), *series[-k:]]

    result = {"recordings": names, "positions": [f"{i}" for i in range(k)] + ["middle"] + [f"{i}" for i in range(-k, 0)],
              "speed_px": [float(v) for v in np.median([ends(s) for s in speeds], 0)], "segmentations": []}
    scale = [np.array([_frame_noise(e) for e in ref]) for ref in errors[0]]  # the default's (C,), each recording
    for changes, out in zip(settings, errors):
        summed = [np.nansum(((e - np.nanmedian(e, 1, keepdims=True)) / s[:, None]) ** 2, 0) for e, s in zip(out, scale)]
        noise = np.median([np.array([_frame_noise(e) for e in own]) / s for own, s in zip(out, scale)], 0)
        result["segmentations"].append({"settings": changes, "error": [float(v) for v in np.median([ends(z) for z in summed], 0)],
                                        "noise_over_default": dict(zip(CHANNELS, (float(v) for v in noise)))})
        print(changes, " ".join(f"{v:.1f}" for v in result["segmentations"][-1]["error"]), flush=True)
    return result


RESEGMENT_MARGIN_PX = 12  # resegment: the exact coverage's crop about the true mask, beyond the blur's reach
RESEGMENT_FULL = 0.98  # resegment: an exact coverage this full is the object's own colour


def _composite(frame: np.ndarray, background: np.ndarray, cover: np.ndarray) -> np.ndarray:
    """(H, W, 3) float picture ``B (1 - a) + F a`` of one (H, W, 3) BGR ``frame``'s object over the
    (H, W, 3) ``background``, at the (H, W) exact coverage ``cover``: ``F`` is the frame's colour at
    the nearest pixel whose coverage is full (:data:`RESEGMENT_FULL`), so the object keeps the
    recording's own shading."""
    from scipy.ndimage import distance_transform_edt

    full = cover >= RESEGMENT_FULL
    if not full.any():  # too thin to hold a full pixel: its own colours
        return background * (1 - cover[..., None]) + frame * cover[..., None]
    _, (rows, cols) = distance_transform_edt(~full, return_indices=True)
    colour = frame[rows, cols].astype(np.float64)
    return background * (1 - cover[..., None]) + colour * cover[..., None]


def resegment(folder: Path, seed: int = 0) -> dict:
    """How much of the segmentation's error on a recording would segmenting a picture made like it
    predict? The exposure's exact average coverage at the true poses (:func:`_exact_coverage`) is
    laid over the background the segmentation estimates, in the frame's own object colours
    (:func:`_composite`), with the recording's sensor noise (``seed``); the picture is stored
    through the recording's codec and crf ("encoded", ``make_recordings.VideoWriter``) and as
    lossless PNG frames ("lossless"), and without the noise as lossless PNG frames ("clean"), and
    each is segmented with the default settings (albedo pass), as the video is. Per channel (:data:`torchfit.residuals.CHANNELS`), against the exact
    exposure average: the video's error ``e``, the picture's ``b``, and for ``e`` and ``e - b`` the
    noise floor (:func:`_frame_noise`), the slow part (:func:`_slow` about the median) and the
    spread about the median; and the correlation of ``e`` with ``b``."""
    import tempfile

    import cv2
    from shake import store_like

    from torchfit.render import RenderMesh
    from torchfit.residuals import CHANNELS
    from torchfit.video import _estimate_background, _read_video

    truth, shape, camera = recording_parts(folder)
    spec = truth["spec"]
    if camera.distorted or spec.get("distortion"):
        raise SystemExit(f"{folder.name}: a lens recording; the exact coverage here takes no distortion")
    if spec.get("transfer", "linear") != "linear":
        raise SystemExit(f"{folder.name}: stored through {spec['transfer']}; the composite here is linear")
    settings = SegmentationSettings(albedo_passes=1)
    frames, _ = _read_video(folder / "video.mp4", 0, None)  # (T, H, W, 3) BGR
    background = _estimate_background(frames, settings).astype(np.float64)
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    sub_position, sub_rotation = _subframe_poses(truth)
    mesh = RenderMesh.from_shape(shape, torch.float64)
    height, width = frames.shape[1:3]
    rng = np.random.default_rng(seed)
    pictures, clean = [], []
    for t, frame in enumerate(frames):
        cover = np.zeros((height, width))
        if true[t].any():
            rows, cols = np.nonzero(true[t])
            y0, x0 = max(rows.min() - RESEGMENT_MARGIN_PX, 0), max(cols.min() - RESEGMENT_MARGIN_PX, 0)
            y1 = min(rows.max() + 1 + RESEGMENT_MARGIN_PX, height)
            x1 = min(cols.max() + 1 + RESEGMENT_MARGIN_PX, width)
            cover[y0:y1, x0:x1] = _exact_coverage(mesh, camera, sub_rotation[t], sub_position[t], x0, y0, y1 - y0, x1 - x0)
        picture = _composite(frame, background, cover)
        clean.append(np.clip(np.rint(picture), 0, 255).astype(np.uint8))
        picture = picture + rng.normal(0.0, 255.0 * spec["noise_sigma"], frame.shape)
        pictures.append(np.clip(np.rint(picture), 0, 255).astype(np.uint8))
    _, averaged = _exact_moments(truth, shape, camera)

    def errors(source: Path, **kind) -> np.ndarray:  # (C, T)
        return _channel_errors(load_observation(str(source), camera=camera, settings=settings, **kind), averaged)

    video = errors(folder / "video.mp4")
    predicted = {}
    with tempfile.TemporaryDirectory() as tmp:
        store_like(Path(tmp) / "picture.mp4", spec, np.stack(pictures))
        predicted["encoded"] = errors(Path(tmp) / "picture.mp4")
        (Path(tmp) / "png").mkdir()
        for name, frames_of in (("lossless", pictures), ("clean", clean)):
            for t, picture in enumerate(frames_of):
                cv2.imwrite(str(Path(tmp) / "png" / f"{t:04d}.png"), picture)
            predicted[name] = errors(Path(tmp) / "png", kind="images", fps=spec["fps"])

    def figures(series: np.ndarray) -> dict:
        finite = series[np.isfinite(series)]
        centred = finite - np.median(finite)
        return {"floor": _frame_noise(series), "slow": float(_slow(centred).std()), "spread": float(centred.std())}

    result = {"frames": int(len(frames)), "channels": {}}
    for c, name in enumerate(CHANNELS):
        row = {"video": figures(video[c])}
        for kind, b in predicted.items():
            ok = np.isfinite(video[c]) & np.isfinite(b[c])
            corrected = np.where(ok, video[c] - b[c], np.nan)
            row[kind] = figures(corrected) | {"correlation": float(np.corrcoef(video[c][ok], b[c][ok])[0, 1])}
        result["channels"][name] = row
        print(folder.name, name, f"floor {row['video']['floor']:.4g}",
              " ".join(f"{k} {row[k]['floor'] / row['video']['floor']:.2f}/{row[k]['slow'] / row['video']['slow']:.2f}"
                       f" r {row[k]['correlation']:+.2f}" for k in predicted), flush=True)
    result["errors"] = {"video": video.tolist(), **{k: v.tolist() for k, v in predicted.items()}}
    return result


REGION_EDGES = (0.02, 0.98)  # regions: the exact coverage's bins (np.digitize) ...
REGIONS = {"interior": 2, "ramp": 1, "outside": 0}  # ... from 0.98 on, between, below 0.02


def _coverage_crops(truth: dict, shape, camera, masks: np.ndarray, kept: list, settings, samples: int):
    """Per frame where the (T, H, W) mask is whole, ``(t, (y0, x0, y1, x1), exact, band, cover)``: the
    crop around the mask (padded by the band and half the frame's travel), the exact coverage there
    (:func:`_exact_coverage`), the segmentation's band and its coverage as the moments take it
    (``kept[t]``, clipped unless the settings say not, within the band); each (h, w)."""
    import torchfit.video as video
    from torchfit.render import RenderMesh

    sub_position, sub_rotation = _subframe_poses(truth)
    mesh = RenderMesh.from_shape(shape, torch.float64)
    velocity = mask_velocity(masks) if settings.coverage_band == "motion" else np.zeros((len(masks), 2))
    steps = settings.band_steps(*masks.shape[1:])
    for t in np.flatnonzero(_whole(masks)):
        rows, cols = np.nonzero(masks[t])
        pad = steps + int(math.ceil(np.abs(velocity[t]).max() / 2)) + 4
        y0, x0 = max(rows.min() - pad, 0), max(cols.min() - pad, 0)
        y1, x1 = min(rows.max() + pad + 1, masks.shape[1]), min(cols.max() + pad + 1, masks.shape[2])
        exact = _exact_coverage(mesh, camera, sub_rotation[t], sub_position[t], x0, y0, y1 - y0, x1 - x0, samples)
        band = video.motion_band(masks[t], steps, velocity[t])[y0:y1, x0:x1]
        cover = (np.clip(kept[t], 0.0, 1.0) if settings.coverage_clip else kept[t])[y0:y1, x0:x1] * band
        yield t, (y0, x0, y1, x1), exact, band, cover


def regions(folder: Path, settings=None, samples: int = 4) -> dict:
    """Where the soft coverage's centroid error lives. Per frame where the mask is whole, the
    segmentation's coverage (clipped to [0, 1], within its band, as its moments take it) minus the
    exact coverage (:func:`_exact_coverage`, the exposure's average of the true silhouette at the
    recording's sub-frames, ``samples`` x ``samples`` a pixel). Split by the exact coverage at
    :data:`REGION_EDGES` into :data:`REGIONS`, each region's share of the centroid error
    ``sum e (x - c) / A`` (px) and of the area ``sum e / A``, with :func:`_stats` over the frames,
    and the region's mean and mean absolute per-pixel error. ``centroid_if_independent``: the RMS
    per axis the same per-pixel errors would give with independent random signs,
    ``sqrt(sum e^2 |x - c|^2 / 2) / A``: an error far above it is correlated from pixel to pixel
    (or systematic), not each pixel's own noise. ``total``: the three summed. Pinhole recordings
    only."""
    settings = settings or SegmentationSettings()
    truth, shape, camera = recording_parts(folder)
    if camera.distorted:
        raise SystemExit("a lens recording: the exact coverage here takes no distortion")
    masks, kept, _ = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    shares = {name: [] for name in REGIONS}  # per frame (cx, cy, area, mean error, mean |error|, independent)
    for _, _, exact, _, cover in _coverage_crops(truth, shape, camera, masks, kept, settings, samples):
        h, w = exact.shape
        error, area = cover - exact, exact.sum()
        v, u = np.mgrid[0:h, 0:w]
        cu, cv = (exact * u).sum() / area, (exact * v).sum() / area
        region = np.digitize(exact, REGION_EDGES)
        for name, index in REGIONS.items():
            inside = region == index
            e = error * inside
            shares[name].append(((e * (u - cu)).sum() / area, (e * (v - cv)).sum() / area, e.sum() / area,
                                 float(error[inside].mean()) if inside.any() else 0.0,
                                 float(np.abs(error[inside]).mean()) if inside.any() else 0.0,
                                 np.sqrt((e**2 * ((u - cu) ** 2 + (v - cv) ** 2)).sum() / 2) / area))
    out = {"frames": len(shares["ramp"])}
    for name, rows in shares.items():
        rows = np.array(rows)
        out[name] = {"centroid_x": _stats(rows[:, 0]), "centroid_y": _stats(rows[:, 1]), "area": _stats(rows[:, 2]),
                     "pixel_error_mean": float(rows[:, 3].mean()), "pixel_error_abs": float(rows[:, 4].mean()),
                     "centroid_if_independent": float(np.sqrt(np.mean(rows[:, 5] ** 2)))}
    total = np.sum([np.array(rows)[:, :3] for rows in shares.values()], 0)
    out["total"] = {"centroid_x": _stats(total[:, 0]), "centroid_y": _stats(total[:, 1]), "area": _stats(total[:, 2])}
    return out


# contrast-oracle: the shares of a frame's ramp pixels (the lowest in contrast, or drawn at random)
# replaced by the exact coverage
ORACLE_SHARES = (0.1, 0.25, 0.5)


def _oracle_errors(cover: np.ndarray, exact: np.ndarray, level: np.ndarray, ramp: np.ndarray,
                   rng: np.random.Generator) -> dict:
    """:func:`contrast_oracle`'s figures for one frame's (h, w) crop: ``cover`` the coverage as the
    moments take it, ``exact`` the exact coverage, ``level`` each pixel's contrast and ``ramp`` (bool)
    the pixels that may be replaced. Label -> the (x, y) centroid error (px, against the exact
    coverage's centroid, divided by its area) with no pixel replaced (``as segmented``), with each
    share of the ramp replaced by the exact coverage, lowest in ``level`` first (``lowest q``; ties
    in pixel order) or drawn at random (``random q``), and with all of it (``ramp exact``)."""
    h, w = exact.shape
    area = exact.sum()
    v, u = np.mgrid[0:h, 0:w]
    cu, cv = (exact * u).sum() / area, (exact * v).sum() / area

    def centroid_error(replaced: np.ndarray) -> tuple[float, float]:
        e = np.where(replaced.reshape(h, w), exact, cover) - exact
        return float((e * (u - cu)).sum() / area), float((e * (v - cv)).sum() / area)

    order = np.flatnonzero(ramp.ravel())
    by_contrast = order[np.argsort(level.ravel()[order], kind="stable")]
    drawn = rng.permutation(order)
    out = {"as segmented": centroid_error(np.zeros(ramp.size, dtype=bool))}
    for kind, ranked in (("lowest", by_contrast), ("random", drawn)):
        for q in ORACLE_SHARES:
            replaced = np.zeros(ramp.size, dtype=bool)
            replaced[ranked[:int(round(q * len(order)))]] = True
            out[f"{kind} {q:g}"] = centroid_error(replaced)
    out["ramp exact"] = centroid_error(ramp.ravel())
    return out


def contrast_oracle(folder: Path, settings=None, samples: int = 4, seed: int = 0) -> dict:
    """Is the coverage's centroid error where the colour contrast is low, and how much would a
    reading of those pixels remove?

    Per frame where the mask is whole (as :func:`regions`), the centroid error of the segmentation's
    coverage (clipped, within its band) against the exact coverage; then the same with a share
    (:data:`ORACLE_SHARES`) of the frame's ramp pixels (exact coverage 0.02-0.98, within the band)
    replaced by the exact coverage: the share lowest in local object-background contrast ``|F - B|``
    (the segmentation's own :func:`torchfit.video._local_contrast`, grey levels in luma/chroma;
    0 where the shading has no support), and the same share drawn at random. The first is an
    oracle's floor for any method that reads low-contrast pixels better (weights them by their
    contrast, or fills them from a model); if it beats the random draw by little, the error is not
    where the contrast is low. ``ramp exact``: every ramp pixel replaced. Centroid figures are
    :func:`_stats` of (T,) px; ``contrast`` the median ``|F - B|`` at each share's cut.
    Pinhole recordings only."""
    import torchfit.video as video

    settings = settings or SegmentationSettings()
    truth, shape, camera = recording_parts(folder)
    if camera.distorted:
        raise SystemExit("a lens recording: the exact coverage here takes no distortion")
    contrasts = []
    original = video._local_contrast

    def watched(*args, **kwargs):
        contrast, support = original(*args, **kwargs)
        contrasts.append(np.sqrt((contrast**2).sum(-1)) * support)
        return contrast, support

    video._local_contrast = watched
    try:
        masks, kept, _ = segment_watching(folder, "_local_shading_coverage", lambda coverage: coverage, settings)
    finally:
        video._local_contrast = original
    if len(contrasts) != len(kept):
        raise RuntimeError(f"{folder.name}: {len(contrasts)} contrasts for {len(kept)} coverages")
    rng = np.random.default_rng(seed)
    labels = (["as segmented"] + [f"lowest {q:g}" for q in ORACLE_SHARES] + [f"random {q:g}" for q in ORACLE_SHARES]
              + ["ramp exact"])
    errors = {label: [] for label in labels}
    cuts = {q: [] for q in ORACLE_SHARES}
    for t, (y0, x0, y1, x1), exact, band, cover in _coverage_crops(truth, shape, camera, masks, kept, settings,
                                                                   samples):
        level = contrasts[t][y0:y1, x0:x1]
        ramp = band & (exact > REGION_EDGES[0]) & (exact < REGION_EDGES[1])
        for label, error in _oracle_errors(cover, exact, level, ramp, rng).items():
            errors[label].append(error)
        order = np.sort(level[ramp])
        for q in ORACLE_SHARES:
            if round(q * len(order)):
                cuts[q].append(float(order[int(round(q * len(order))) - 1]))
    out = {"frames": len(errors["as segmented"])}
    for label, rows in errors.items():
        rows = np.array(rows)
        out[label] = {"centroid_x": _stats(rows[:, 0]), "centroid_y": _stats(rows[:, 1])}
    out["contrast"] = {f"lowest {q:g}": float(np.median(c)) if c else None for q, c in cuts.items()}
    return out


def gravity_known(folder: Path) -> dict:
    """Would knowing gravity's direction let the video see a drag or a lift? discover as by default
    (``concealed.py --albedo-passes 1 --exposure --exposure-fraction 0.5 --exposure-taps 0
    --fit-exposure --robust 2 --backcast --search-final 12``) with gravity held at the engine's
    (``truth.json``'s tilt and roll): every refit starts there and holds its two columns (an upper
    bound: a level or a phone's sensor knows it to a fraction of a degree, not exactly). Its
    discover.json goes to results/diagnose_gravity-known_<set>_<name>/; returns each round-one
    candidate's ΔBIC, held-out gain, fitted value and detection limit, and the verdict."""
    from concealed import run_one

    truth = json.loads((folder / "truth.json").read_text())
    angles = torch.tensor([[math.radians(truth["tilt_deg"]), math.radians(truth["roll_deg"])]], dtype=torch.float64)
    frozen, starts = dv.VideoProblem._frozen, dv.VideoProblem.search_starts

    def held(self, model):
        out = frozen(self, model)
        out[dv._state_columns(model.cands)["gravity_angles"]] = True
        return out

    def at_truth(self, result, count):
        models = starts(self, result, count)
        for model in models:
            model.cands.gravity_angles = angles.to(model.cands.gravity_angles)
        return models

    out = HERE / "results" / f"diagnose_gravity-known_{folder.parent.name}_{folder.name}"
    dv.VideoProblem._frozen, dv.VideoProblem.search_starts = held, at_truth
    try:
        content = run_one(folder, out, albedo_passes=1, exposure=True, exposure_fraction=0.5, exposure_taps=0,
                          fit_exposure=True, robust=2.0, backcast=True, search_final=12)
    finally:
        dv.VideoProblem._frozen, dv.VideoProblem.search_starts = frozen, starts
    rounds = {name: {"delta_bic": s[0]["delta_bic"], "heldout_gain": s[0]["heldout_gain"],
                     "fitted": {p: v["value"] for p, v in s[0]["params"].get(name, {}).items()},
                     "detectable_above": s[0].get("detectable_above")}
              for name, s in content["effects"].items() if s}
    return {"verdict": content["verdict"], "truth_effects": content.get("truth_effects"), "round_one": rounds}


class _NoiseSet(Exception):
    """Raised by :func:`jump_scores`'s patch once discover has set its noise floors."""

    def __init__(self, video: dv.VideoProblem):
        super().__init__("noise set")
        self.video = video


def jump_scores(folder: Path) -> dict:
    """The jump test's scores, per channel and frame, as discover's default run meets them: the
    default's path (``concealed.py`` with the default's flags) up to where the baseline's noise
    floors are set from the search's best (``VideoProblem._set_noise``), then stopped. Per
    channel, each frame's jump off the line through its neighbours in jitter standard
    deviations (None: a frame not used), and the channel's residuals themselves (``values``,
    the observed minus the search's best) with their jitter floor (``sigma``,
    :func:`torchfit.residuals.noise_floor` on the used frames); the frames are the video's."""
    import concealed

    from torchfit.residuals import noise_floor

    original, seen, spans = dv.VideoProblem._set_noise, [], []
    discover = concealed.discover_video

    def spanned(problem, observation, span, **kwargs):  # the run's own span, not a second segmentation
        spans.append(span)
        return discover(problem, observation, span, **kwargs)

    def stop(self, model):
        channels_of = self._channels_of

        def captured(*args, **kwargs):  # the residual channels _set_noise tests, the first call's
            out = channels_of(*args, **kwargs)
            seen.append({k: v[0].detach().cpu().numpy() for k, v in out.items()})
            return out

        self._channels_of = captured
        original(self, model)
        raise _NoiseSet(self)

    dv.VideoProblem._set_noise, concealed.discover_video = stop, spanned
    try:
        concealed.run_one(folder, HERE / "results" / "diagnose_jump-scores_scratch", albedo_passes=1, exposure=True,
                exposure_fraction=0.5, exposure_taps=0, fit_exposure=True, robust=2.0, backcast=True,
                search_final=12)
        raise RuntimeError(f"{folder}: discover ended without setting its noise floors")
    except _NoiseSet as stopped:
        video = stopped.video
    finally:
        dv.VideoProblem._set_noise, concealed.discover_video = original, discover
    span = spans[0]
    row = {"frames": [int(f) for f in span], "outliers": [int(span[i]) for i in video.outliers],
           "scores": {name: [None if not np.isfinite(v) else round(float(v), 3) for v in scores]
                      for name, scores in video.jump_scores.items()}}
    used = np.isfinite(next(iter(video.jump_scores.values()))) if video.jump_scores else np.zeros(len(span), bool)
    row["values"] = {name: [float(v) if ok else None for v, ok in zip(values, used)]
                     for name, values in seen[0].items()}
    row["sigma"] = {name: float(noise_floor(values[used])) for name, values in seen[0].items()}
    print(folder.parent.name, folder.name, "left out", row["outliers"],
          {int(span[i]): video.outlier_jumps(i) for i in video.outliers}, flush=True)
    return row


def lens_residual(folder: Path, settings=None) -> dict:
    """Is a lens left after undistortion? The soft coverage's centroids (the segmentation's own
    moments, each frame's coverage undistorted through the calibrated camera, truth.json's
    ``camera_true``, where it has distortion) against the exact exposure average's
    (:func:`_exact_moments`, the pinhole camera), per frame where the mask is whole, fitted by
    :func:`radial_fit`. Its standard error takes the frames as independent, which the
    segmentation's slow error is not, so it is a lower bound."""
    import torchfit.video as video
    from torchfit.camera import Camera

    truth, shape, pinhole = recording_parts(folder)
    lens = Camera.from_dict(truth["camera_true"]) if "camera_true" in truth else pinhole
    frames, _ = video._read_video(folder / "video.mp4", 0, None)
    seg = video._segment(frames, settings or SegmentationSettings(),
                         undistort=video._undistort_maps(lens) if lens.distorted else None)
    raw = np.asarray(seg["coverage_moments"])
    _, exact = _exact_moments(truth, shape, pinhole)
    exact = exact.numpy()
    whole = _whole(seg["masks"])
    seen, true = raw[whole, 1:3] / raw[whole, :1], exact[whole, 1:3] / exact[whole, :1]
    out = {"frames": int(whole.sum()), "k1": float(lens.dist_coeffs[0]) if lens.distorted else 0.0,
           **radial_fit(seen, true, np.asarray(pinhole.K))}
    if lens.distorted:
        out["maps_disagreement_px"] = _maps_disagreement(truth, lens)
    return out


def _maps_disagreement(truth: dict, lens) -> float:
    """The largest distance (px) between an undistorted pixel and where the generator's lens
    (make_recordings.distortion_maps: distorted pixel -> its wide pinhole render) sends the point
    that OpenCV's undistortion maps (torchfit's, :func:`torchfit.video._undistort_maps`) take it
    to, over the pixels whose distorted place lies inside the frame: 0 when the two lenses agree."""
    import cv2
    import make_concealed  # noqa: F401  (puts make_recordings on the path)
    import make_recordings as mr

    import torchfit.video as video

    spec = mr.RecordingSpec(**truth["spec"])
    to_wide = mr.distortion_maps(spec)
    width, height, _ = mr.render_geometry(spec)
    to_distorted = video._undistort_maps(lens)
    wide = [cv2.remap(m, *to_distorted, cv2.INTER_LINEAR) for m in to_wide]
    v, u = np.mgrid[0:spec.height, 0:spec.width].astype(np.float64)
    K = np.asarray(lens.K)
    off = np.hypot(wide[0] - (u + (width - 1) / 2 - K[0, 2]), wide[1] - (v + (height - 1) / 2 - K[1, 2]))
    inside = ((to_distorted[0] > 1) & (to_distorted[0] < spec.width - 2)
              & (to_distorted[1] > 1) & (to_distorted[1] < spec.height - 2))
    return float(off[inside].max())


def radial_fit(seen: np.ndarray, true: np.ndarray, K: np.ndarray) -> dict:
    """(N, 2) centroids ``seen`` against (N, 2) ``true`` (px) fitted by an offset per axis plus
    ``d k1`` times ``f x_n r_n^2`` (the shift a change ``d k1`` of the radial term makes at each true
    centroid, normalised coordinates by the (3, 3) ``K``): ``residual_k1`` and its standard error
    (points taken as independent), ``signature_px`` (the largest ``|f x_n r_n^2|``), ``offset_px``
    and the RMS left (``centroid_rms_px``)."""
    normal = (true - K[:2, 2]) / K[0, 0]
    signature = K[0, 0] * normal * (normal**2).sum(1, keepdims=True)  # (N, 2) px per unit k1
    design = np.zeros((2 * len(seen), 3))
    design[0::2, 0], design[1::2, 1], design[:, 2] = 1.0, 1.0, signature.ravel()
    error = (seen - true).ravel()
    beta, *_ = np.linalg.lstsq(design, error, rcond=None)
    rest = error - design @ beta
    covariance = rest @ rest / (len(error) - 3) * np.linalg.inv(design.T @ design)
    return {"residual_k1": float(beta[2]), "residual_k1_std": float(np.sqrt(covariance[2, 2])),
            "signature_px": float(np.abs(signature).max()), "offset_px": beta[:2].tolist(),
            "centroid_rms_px": float(np.sqrt(np.mean(rest**2)))}


def _setting_args(args: list[str]) -> dict:
    """The ``SETTING=V`` arguments among ``args`` as segmentation settings (:func:`_setting_value`)."""
    return {k: _setting_value(v) for k, v in (a.split("=") for a in args if "=" in a)}


def _setting_label(changes: dict) -> str:
    """A results file name's part for segmentation settings: ``_<name><value>`` each."""
    return "".join(f"_{k}{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else f"_{k}{v}"
                   for k, v in changes.items())


def main(argv: list[str]) -> None:
    remakes = {"sources": (sources, SOURCES, ERROR_KEYS), "codec": (codec, CODECS, ERROR_KEYS + ("bits_per_pixel",)),
               "stretch-sources": (stretch_sources, None, None), "regions-sources": (regions_sources, None, None)}
    if argv[:1] and argv[0] in remakes and len(argv) > 2:
        command, columns, keys = remakes[argv[0]]
        file = HERE / "results" / f"diagnose_{argv[0].replace('-', '_')}.json"
        result = json.loads(file.read_text()) if file.exists() else {}
        result.update(command(int(argv[1]), argv[2:]))
        if columns is not None:  # the means over the recordings remade every way
            rows = [r for k, r in result.items() if k != "mean" and set(r) == set(columns)]
            result["mean"] = _means(rows, columns, keys) | {"recordings": len(rows)}
            print(json.dumps(result["mean"], indent=1))
        file.write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["ramp"] and len(argv) > 2:
        file = HERE / "results" / "diagnose_ramp.json"
        result = json.loads(file.read_text()) if file.exists() else {}
        changes = _setting_args(argv[3:])
        label = " ".join(f"{k}={v:g}" for k, v in changes.items())
        for source in [a for a in argv[3:] if "=" not in a] or ["as recorded", "motion blur alone"]:
            row = ramp(int(argv[1]), argv[2], source, changes)
            result.setdefault(f"{argv[1]}/{argv[2]}", {})[f"{source} {label}".strip()] = row
            print(argv[1], argv[2], source, label, json.dumps(row), flush=True)
        file.write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["chroma"] and len(argv) > 1:
        result = chroma(argv[1:])
        print(json.dumps(result["mean"], indent=1))
        (HERE / "results" / "diagnose_chroma.json").write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["sets"] and len(argv) > 1:
        file = HERE / "results" / "diagnose_sets.json"  # the sets named replace their own entries
        result = (json.loads(file.read_text()) if file.exists() else {}) | sets(argv[1:])
        print(json.dumps({name: rows["mean"] for name, rows in result.items()}, indent=1))
        file.write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["end-frames"] and len(argv) > 1:
        changes = [_setting_args([a]) for a in argv[2:]]
        if any(not c for c in changes):
            sys.exit(f"end-frames: SET then SETTING=V..., got {' '.join(argv[1:])}")
        if not (HERE / argv[1]).is_dir():
            sys.exit(f"end-frames: no set of recordings {HERE / argv[1]}: make it with make_concealed.py")
        for c in changes:  # a bad setting stops here, before the recordings are read
            try:
                SegmentationSettings(**c)
            except (TypeError, ValueError) as err:
                sys.exit(f"end-frames: {' '.join(f'{k}={v}' for k, v in c.items())}: {err}")
        result = end_frames(HERE / argv[1], changes)
        label = "".join(_setting_label(c) for c in changes)
        (HERE / "results" / f"diagnose_end-frames_{argv[1]}{label}.json").write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["frame-correlation"] and len(argv) > 1:
        missing = [name for name in argv[1:] if not (HERE / name).is_dir()]
        if missing:
            sys.exit(f"frame-correlation: no set of recordings {HERE / missing[0]}: make it with make_concealed.py")
        result = frame_correlation([HERE / name for name in argv[1:]])
        (HERE / "results" / f"diagnose_frame-correlation_{'_'.join(argv[1:])}.json").write_text(json.dumps(result, indent=1))
        return
    if argv[:1] == ["lens-masks"] and len(argv) > 2:
        file = HERE / "results" / "diagnose_lens_masks.json"
        result = json.loads(file.read_text()) if file.exists() else {}
        for name in argv[2:]:
            folder = Path(argv[1]) / name
            folder = folder if folder.is_absolute() else HERE / folder
            result[f"{argv[1]}/{name}"] = row = lens_masks(folder)
            print(argv[1], name, json.dumps(row), flush=True)
        file.write_text(json.dumps(result, indent=1))
        return
    commands = {"segmentation": segmentation, "clock": clock, "stall": stall, "jacobian": jacobian,
                "coverage": coverage, "heldout": heldout, "heldout-channels": heldout_channels,
                "heldout-blur": lambda folder, effect, **held: heldout_channels(folder, effect, blurred=True, **held),
                "heldout-swap": heldout_swap, "blur": blur, "stretch": stretch,
                "contrast": contrast, "clip": clip, "search": search, "exposure": exposure,
                "blur-estimate": blur_estimate, "blur-speed": blur_speed, "exact-coverage": exact_coverage, "area": area,
                "spread-stall": spread_stall, "baseline-starts": baseline_starts,
                "shape-frames": shape_frames, "error-speed": error_speed, "regions": regions,
                "contrast-oracle": contrast_oracle, "lens-residual": lens_residual, "gravity-known": gravity_known,
                "jump-scores": jump_scores,
                "resegment": resegment}
    if len(argv) < 3 or argv[0] not in commands:
        sys.exit(__doc__)
    command, folder = argv[0], HERE / argv[1]
    # exposure: fractions=F1,F2,... in place of EXPOSURE_GRID
    fractions = [a for a in argv[2:] if a.startswith("fractions=")] if command == "exposure" else []
    # exact-coverage: parts=P1,P2 of COVERAGE_PARTS (default all)
    parts = [a for a in argv[2:] if a.startswith("parts=")] if command == "exact-coverage" else []
    # heldout-blur: exposure=F, the exposure held at F instead of fitted
    held = [a for a in argv[2:] if a.startswith("exposure=")] if command == "heldout-blur" else []
    # heldout-channels, heldout-blur: robust=K, Huber's loss at K noise floors
    robust = [a for a in argv[2:] if a.startswith("robust=")] if command in ("heldout-channels", "heldout-blur") else []
    # heldout-channels, heldout-blur, heldout-swap: backcast=true, the first quarter held out as well
    backcast = ([a for a in argv[2:] if a.startswith("backcast=")]
                if command in ("heldout-channels", "heldout-blur", "heldout-swap") else [])
    if backcast and backcast[-1] not in ("backcast=true", "backcast=false"):
        sys.exit(f"{command}: backcast= takes true or false, got {backcast[-1]}")
    # heldout-channels: masks=true, the engine's exact masks in place of the segmentation
    exact = [a for a in argv[2:] if a.startswith("masks=")] if command == "heldout-channels" else []
    if exact and exact[-1] not in ("masks=true", "masks=false"):
        sys.exit(f"{command}: masks= takes true or false, got {exact[-1]}")
    argv = [a for a in argv if a not in fractions + parts + held + robust + backcast + exact]
    several = command in ("segmentation", "coverage", "blur", "stretch", "contrast", "clip", "search", "exposure",
                          "blur-estimate", "blur-speed", "exact-coverage", "area", "spread-stall", "baseline-starts",
                          "shape-frames", "error-speed", "regions", "contrast-oracle", "lens-residual", "jump-scores",
                          "resegment")
    # the commands that take segmentation settings, SETTING=V after the names (e.g. albedo_passes=1)
    changes = (_setting_args(argv[2:]) if command in ("blur", "search", "exposure", "blur-estimate", "blur-speed",
                                                      "exact-coverage", "area", "spread-stall",
                                                      "baseline-starts", "heldout-blur", "shape-frames",
                                                      "error-speed", "regions", "contrast-oracle",
                                                      "lens-residual") else {})
    if command == "heldout-blur" and changes:  # the blurred path's albedo pass, unless set
        changes = {"albedo_passes": 1} | changes
    if command == "search" and not changes:
        sys.exit("diagnose.py search needs the changed segmentation's settings, e.g. albedo_passes=1")
    names = [a for a in argv[2:] if "=" not in a] if several else argv[2:3]
    label = _setting_label(changes)
    if fractions:
        grid = tuple(float(f) for f in fractions[-1].split("=", 1)[1].split(","))
        label += "_fractions" + "_".join(f"{f:g}" for f in grid)
    chosen = tuple(parts[-1].split("=", 1)[1].split(",")) if parts else COVERAGE_PARTS
    if not set(chosen) <= set(COVERAGE_PARTS + SHAPE_PARTS):
        sys.exit(f"exact-coverage: parts= takes some of {', '.join(COVERAGE_PARTS + SHAPE_PARTS)}, "
                 f"got {','.join(chosen)}")
    if parts:
        label += "_exact_" + "_".join(chosen)
    if held:
        label += "_" + held[-1].replace("=", "")
    if robust:
        label += "_" + robust[-1].replace("=", "")
    if backcast == ["backcast=true"]:
        label += "_backcast"
    if exact == ["masks=true"]:
        label += "_true_masks"
    for name in names:
        if not (folder / name / "truth.json").exists():
            sys.exit(f"no concealed recording {folder / name}: make it with make_concealed.py")
        extra = {"settings": SegmentationSettings(**changes)} if changes else {}
        if fractions:
            extra["fractions"] = grid
        if parts:
            extra["parts"] = chosen
        if held:
            extra["held_exposure"] = float(held[-1].split("=", 1)[1])
        if robust:
            extra["robust"] = float(robust[-1].split("=", 1)[1])
        if backcast:
            extra["backcast"] = backcast[-1] == "backcast=true"
        if exact:
            extra["true_masks"] = exact[-1] == "masks=true"
        result = commands[command](folder / name, *([] if several else [a for a in argv[3:] if "=" not in a]), **extra)
        print(f"== {command} {argv[1]}/{name}")
        print(json.dumps(result, indent=1, default=float))
        (HERE / "results" / f"diagnose_{command}_{argv[1]}_{name}{label}.json").write_text(
            json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
