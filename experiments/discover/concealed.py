"""Discover on the concealed-effect recordings: the verdict table of experiments/discover/README.md.

    MUJOCO_GL=osmesa python experiments/discover/make_concealed.py   # once (~8 min), git-ignored
    python experiments/discover/concealed.py [names...]              # ~2-6 min per recording, on the masks
    python experiments/discover/concealed.py --albedo-passes 1 --exposure --exposure-fraction 0.5 \
        --exposure-taps 0 --fit-exposure --robust 2 --backcast [names...]  # as the CLI does by default
    python experiments/discover/concealed.py --table                 # the table from the outputs
    python experiments/discover/concealed.py --true-masks [names...] # MuJoCo's true masks instead
    python experiments/discover/concealed.py --shipped [names...]    # the shipped recordings (hide nothing)
    python experiments/discover/concealed.py --fresh K [names...]    # fresh set K (make_concealed.py --fresh K)
    python experiments/discover/concealed.py --shutter [--true-masks] # the rolling-shutter set, + rolling_shutter
    python experiments/discover/concealed.py --with rolling_shutter [...] # one more candidate (results/..._with_<name>/)
    python experiments/discover/concealed.py --chroma-weight W [...]  # segmented with another chroma weight
    python experiments/discover/concealed.py --albedo-passes N [...]  # the albedo from covered pixels (N passes)
    python experiments/discover/concealed.py --exposure [...]         # the soft coverage against the exposure's average
    python experiments/discover/concealed.py --exposure --coverage-near-px N [...]  # the coverage counted within N px of the mask
    python experiments/discover/concealed.py --sharp [--fresh K] [...] # the set remade without motion blur (make_concealed.py --sharp)
    python experiments/discover/concealed.py --sharp --exposure --shuffle-error S [...] # its segmentation error, shuffled in time, on the exact masks
    python experiments/discover/concealed.py --search-final N [...]  # the baseline search polishes up to N distinct minima
    python experiments/discover/concealed.py --true-masks --edge-px E [...] # another edge term in the noise floor
    python experiments/discover/concealed.py --transfer T [--read-as R] [...] # the set stored through camera curve T (make_concealed.py --transfer T), segmented as T (or as R)
    python experiments/discover/concealed.py --compare REV [--fresh K] # rows rerun since git REV, before and now
    python experiments/discover/concealed.py --scoreboard            # the targets over every stored set
    python experiments/discover/concealed.py --scoreboard --chroma-weight W  # default weight against W, side by side
    python experiments/discover/concealed.py --scoreboard --albedo-passes N  # the default segmentation against N passes
    python experiments/discover/concealed.py --scoreboard [--albedo-passes N] --exposure  # the default against the exposure
    python experiments/discover/concealed.py --scoreboard --with NAME  # without and with one more candidate, side by side
    python experiments/discover/concealed.py --scoreboard --edge-px E  # exact masks at EDGE_PX and at E, side by side
    python experiments/discover/concealed.py --rules                 # what each test alone kept out, right and wrong

Each recording gets `python -m torchfit experiment=discover`'s outputs in
experiments/discover/results/concealed/<name>/ (discover.json, residuals.png, report.txt); the
table (verdict against truth, held-out error before and after, fitted coefficients against the
engine's) is printed and written to results/concealed/table.md and summary.json. With
``--true-masks`` discover sees the engine's exact masks instead of the video's segmentation
(results/concealed_true_masks/): what the physics, the noise model and the criterion do when
the segmentation makes no error. With ``--shipped`` it runs on the recordings shipped in
torchfit/recordings (results/shipped/), which hide nothing and calibrated the noise model: what
segmentation error alone scores there. With ``--fresh K`` it runs on the fresh set K made by
``make_concealed.py --fresh K`` (same recipes, other throws and background; results/concealed_fresh<K>/,
with ``--true-masks`` results/concealed_fresh<K>_true_masks/): a check of every choice made while
looking at the first set.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import zlib
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import numpy as np
from true_masks import fps_factor, fresh_folder, load_problem, recording_parts, with_error_shuffled

import torchfit
from torchfit.discover import without_weakest_block
from torchfit.discover_video import (
    DEFAULT_CANDIDATES,
    EDGE_FORM,
    EDGE_PX,
    JUMP_SIGMAS,
    VIDEO_EFFECTS,
    VIDEO_SELECTION,
    across_velocity,
    angle_to_line,
    discover_video,
    edge_setting,
    least_seen,
    lens_shift,
    lift_across,
)
from torchfit.camera import Camera
from torchfit.effects import EFFECTS
from torchfit.search import Exposure, SearchSettings
from torchfit.shape import load_shape
from torchfit.video import TRANSFERS, SegmentationSettings

HERE = Path(__file__).resolve().parent  # also holds true_masks.py (load_problem)
RECORDINGS = HERE / "recordings"
OUT = HERE / "results" / "concealed"
CANDIDATES = DEFAULT_CANDIDATES  # inertia left out: see the README
SHIPPED = ("tshape", "box_fast", "tshape_intermediate", "cylinder")  # the noise model's calibration recordings


def run_one(folder: Path, out: Path, *, true_masks: bool = False, chroma_weight: float | None = None,
            candidates: tuple[str, ...] = CANDIDATES, edge_px: float | str = "auto", albedo_passes: int | None = None,
            transfer: str | None = None, exposure: bool = False, exposure_fraction: float | None = None,
            coverage_near_px: int | None = None, coverage_clip: bool | None = None,
            fit_exposure: bool = False, point_spread: tuple[float, float] | None = None,
            baseline_starts: int = 1, exposure_taps: int | None = None, coverage_band: str | None = None,
            shading_fit: str | None = None, well_posed_grey: float | None = None,
            interior_shading: bool | None = None, speed_noise: bool = False, heldout_margin: float | None = None, robust: float | None = None, declare_lens: bool = False,
            backcast: bool = False, search_final: int | None = None,
            jump_sigmas: float | None = JUMP_SIGMAS, jump_one_at_a_time: bool = False,
            jump_neighbours: int = 0, jump_refined: bool = False, shuffle_error: int | None = None) -> dict:
    """Discover on one recording ``folder``, written to ``out``. ``shuffle_error``: a seed; the soft
    coverage's moments are then the engine's exact masks' carrying the segmentation's own
    per-frame error in a shuffled order (:func:`true_masks.with_error_shuffled`; a set made
    without blur, whose exact masks are its frames' instants)."""
    truth, shape, camera = recording_parts(folder)
    if declare_lens:  # the camera as calibrated (truth.json camera_true): a lens the recording hides is known
        camera = Camera.from_dict(truth["camera_true"])
        truth = {**truth, "effects": {k: v for k, v in truth.get("effects", {}).items() if k != "lens_distortion"}}
    changes = {k: v for k, v in (("chroma_weight", chroma_weight), ("albedo_passes", albedo_passes),
                                 ("transfer", transfer), ("coverage_near_px", coverage_near_px),
                                 ("coverage_clip", coverage_clip), ("coverage_band", coverage_band),
                                 ("shading_fit", shading_fit), ("well_posed_grey", well_posed_grey),
                                 ("interior_shading", interior_shading)) if v is not None}
    settings = SegmentationSettings(**changes) if changes else None
    observation, problem, span = load_problem(folder, shape, camera, true_masks, settings)
    if shuffle_error is not None:
        masks = np.load(folder / "masks.npz")["masks"].astype(bool)
        observation = with_error_shuffled(observation, masks, (shuffle_error, zlib.crc32(folder.name.encode())))
    rules = VIDEO_SELECTION if heldout_margin is None else replace(VIDEO_SELECTION, heldout_margin=heldout_margin)
    return discover_video(problem, observation, span, candidates=candidates, settings=rules,
                          edge_px=edge_px, truth=truth, out_dir=out, overlay=False, progress=print,
                          exposure=recording_exposure(truth, exposure_fraction, exposure_taps) if exposure else None,
                          fit_exposure=fit_exposure, point_spread=point_spread, baseline_starts=baseline_starts,
                          speed_noise=speed_noise, robust=robust, backcast=backcast,
                          jump_sigmas=jump_sigmas, jump_one_at_a_time=jump_one_at_a_time,
                          jump_neighbours=jump_neighbours, jump_refined=jump_refined,
                          search=SearchSettings() if search_final is None else SearchSettings(final=search_final))


def robust_suffix(robust: float | None) -> str:
    """The results folder's suffix of a run whose criterion is Huber's loss at ``robust`` noise
    units (none for squares)."""
    return "" if robust is None else f"_huber{robust:g}"


def jump_suffix(jump_sigmas: float | None, one_at_a_time: bool = False, neighbours: int = 0,
                refined: bool = False) -> str:
    """The results folder's suffix of a run whose jump test leaves frames out at ``jump_sigmas``
    jitter standard deviations (``discover_video(jump_sigmas=...)``): none at the default
    (``JUMP_SIGMAS``), ``_nojump`` where no frame is left out (None), else ``_jump<S>``; then
    ``_1by1`` where they are left out worst first (``jump_one_at_a_time``), ``_nb<K>`` where K
    frames on either side of each go with it (``jump_neighbours``), and ``_refj`` where the test
    is judged on the baseline refitted to every frame (``jump_refined``)."""
    if jump_sigmas is None:
        return "_nojump"
    return (("" if jump_sigmas == JUMP_SIGMAS else f"_jump{jump_sigmas:g}") + ("_1by1" if one_at_a_time else "")
            + (f"_nb{neighbours}" if neighbours else "") + ("_refj" if refined else ""))


def backcast_suffix(backcast: bool) -> str:
    """The results folder's suffix of a run whose held-out test also backcasts the first quarter
    (none without)."""
    return "_backcast" if backcast else ""


FIRST_FINAL = 6  # SearchSettings.final when every set's first runs were made


def final_suffix(final: int | None) -> str:
    """The results folder's suffix of a run whose search polishes up to ``final`` distinct minima
    (None: ``SearchSettings``' own): none for :data:`FIRST_FINAL`, so a folder names the final
    its runs used whatever the day's default."""
    final = SearchSettings().final if final is None else final
    return "" if final == FIRST_FINAL else f"_final{final}"


def heldout_suffix(margin: float | None) -> str:
    """The results folder's suffix of a run whose held-out test is the predictive deviance within
    ``margin`` (none for the default rule)."""
    return "" if margin is None else f"_heldout{margin:g}"


def recording_exposure(truth: dict, fraction: float | None = None, taps: int | None = None) -> Exposure:
    """The exposure a generated recording was rendered with (``truth.json``'s ``render``): its
    sub-frames over ``exposure_frac`` of the frame interval, or none for a sharp recording;
    ``fraction`` in place of ``exposure_frac`` (a wrong guess of it) and ``taps`` in place of its
    sub-frames (0: a camera's, as a user who does not know the renderer gives it) when given."""
    rendered = int(truth["render"]["blur_subframes"])
    if fraction is None:
        fraction = float(truth["render"]["exposure_frac"]) if rendered > 1 else 0.0
    if taps is None:
        taps = rendered if rendered > 1 else 0
    return Exposure(fraction, taps)


def exposure_suffix(fraction: float | None, taps: int | None = None) -> str:
    """The results folder's suffix of a run with the exposure: the recording's own, or ``fraction``
    (and ``_taps<T>`` with ``taps`` in place of the recording's sub-frames)."""
    return "_exposure" + ("" if fraction is None else f"{fraction:g}") + ("" if taps is None else f"_taps{taps}")


def segmentation_suffix(albedo_passes: int | None, exposure: bool, exposure_fraction: float | None,
                        coverage_near_px: int | None, coverage_clip: bool | None = None,
                        fit_exposure: bool = False, point_spread: tuple[float, float] | None = None,
                        exposure_taps: int | None = None, coverage_band: str | None = None,
                        shading_fit: str | None = None, well_posed_grey: float | None = None,
                        interior_shading: bool | None = None) -> str:
    """The results folder's suffix of the albedo pass, the exposure (given or fitted from the
    fraction), a fitted point spread (``_spread`` without a prior, ``_spread<M>pm<S>`` with the
    prior ``M ± S`` px^2), the coverage band, its sweep along the motion (``_motionband``), the
    coverage's clip, the local-linear shading (``_linshade``) and the per-pixel fit's trust
    (``_grey<G>``, ``SegmentationSettings.well_posed_grey``) and the shading's support from the
    object's interior (``_interior``, ``SegmentationSettings.interior_shading``) (empty for each
    left at its default)."""
    return ((f"_albedo{albedo_passes}" if albedo_passes is not None else "")
            + (exposure_suffix(exposure_fraction, exposure_taps) if exposure else "")
            + ("_fitted" if fit_exposure else "")
            + ("" if point_spread is None else "_spread" + ("" if math.isinf(point_spread[1])
                                                            else f"{point_spread[0]:g}pm{point_spread[1]:g}"))
            + (f"_near{coverage_near_px}" if coverage_near_px is not None else "")
            + ("_motionband" if coverage_band == "motion" else "")
            + ("_unclipped" if coverage_clip is False else "")
            + ("_linshade" if shading_fit == "linear" else "")
            + (f"_grey{well_posed_grey:g}" if well_posed_grey is not None else "")
            + ("_interior" if interior_shading else ""))


def _aligned(folder: Path, fitted: list[float], true: list[float]) -> list[float]:
    """A body-frame vector fitted in a frame that may differ from the truth's by one of the shape's
    symmetries (a T-handle turned 180 degrees about its stem looks the same): the image closest
    to the true vector."""
    truth = json.loads((folder / "truth.json").read_text())
    symmetries = np.asarray(load_shape(folder / "mesh.obj", density=truth["object"]["density"]).symmetries)
    images = symmetries @ np.asarray(fitted)
    return images[np.argmin(np.linalg.norm(images - np.asarray(true), axis=1))].tolist()


def row(name: str, content: dict, recordings: Path = RECORDINGS) -> dict:
    truth = list(content.get("truth_effects", {}))
    verdict = content["verdict"]
    # right: exactly the hidden effects named (a spurious second name is a wrong verdict too)
    right = sorted(verdict) == sorted(truth)
    first, last = content["models"][0], content["models"][-1]
    params = {}
    for effect in truth:
        fitted = last["params"].get(effect) or {}
        params[effect] = {p: {"fitted": v["value"], "std": v["std"], "true": content["truth_effects"][effect][p]}
                          for p, v in fitted.items()}
        if effect == "com_offset" and "offset" in params[effect]:  # compare modulo the shape's symmetry
            entry = params[effect]["offset"]
            entry["fitted"] = _aligned(recordings / name, entry["fitted"], entry["true"])
        lift = ball_lift(content) if effect == "magnus" else None
        if lift is not None:  # a ball: its lift vector's part across the direction it is seen least
            params[effect] = {"lift_across": lift}
        shift = lens_shift_against_truth(content) if effect == "lens_distortion" and fitted else None
        if shift is not None:  # the lens's shift where the object went farthest, against the engine's lens
            params[effect]["shift_px"] = shift
    # the size each true parameter needed to pass in round one, on this clip (discover's detection limit)
    limits = {effect: content["effects"].get(effect, [{}])[0].get("detectable_above", {}) for effect in truth}
    # round one's strongest candidate, passing or not: how close a control came to a false alarm
    first_round = [(s["delta_bic"], effect, _without_third(s)) for effect, scores in content["effects"].items()
                   for s in scores if not s.get("base")]
    top_bic, top, top_thirds = max(first_round, key=lambda c: c[0]) if first_round else (float("nan"), "", None)
    # run with the evidence-thirds rule (each score then carries its ΔBIC without its weakest third)
    thirds = any("delta_bic_without_block" in s for scores in content["effects"].values() for s in scores)
    return {"recording": name, "truth": truth, "verdict": verdict, "top_delta_bic": [top, top_bic, top_thirds],
            "thirds_rule": thirds, "indistinguishable": content["indistinguishable"],
            "truth_effects": content.get("truth_effects", {}),
            "spin_hidden": spin_hidden(content),
            "verdict_withheld": content.get("verdict_withheld", []), "detectable_above": limits,
            "concealed": content["iou_baseline"]["mean_fitted"] >= 0.9,
            "right": bool(right), "heldout_px_before": first["heldout_centroid_px"],
            "heldout_px_after": last["heldout_centroid_px"], "iou_baseline": content["iou_baseline"],
            "params": params, "seconds": content["seconds"], "edge_px": last.get("edge_px", {}),
            "exposure_baseline": (content.get("exposure_fitted") or [None])[0],
            "outlier_frames": content.get("outlier_frames", []),
            "flagged": flagged(content)}


def flagged(content: dict) -> dict:
    """Whether a run's report located a miss (any channel flagged): the baseline's fit to all
    frames (``located``), the baseline's predictions of the held-out parts (``located_heldout``,
    any part) and the final model's (``located_heldout_after``); None for a run made before the
    predictions were located (2026-11-30)."""
    def any_part(key: str) -> bool | None:
        return None if key not in content else any(part["flagged"] for part in content[key])
    return {"fit": bool(content["located"]["flagged"]), "predicted": any_part("located_heldout"),
            "predicted_after": any_part("located_heldout_after")}


def lens_shift_against_truth(content: dict) -> dict | None:
    """A run's (``discover.json``'s ``content``) lens shift in its final model where the object went
    farthest (``models[].lens_shift``, :func:`torchfit.discover_video.lens_shift`) and the engine's
    lens's shift at the same point: ``{"fitted", "std", "true"}`` px; None unless the final model
    holds a lens and the engine hid one."""
    shift, true = content["models"][-1].get("lens_shift"), (content.get("truth_effects") or {}).get("lens_distortion")
    if shift is None or true is None:
        return None
    return {"fitted": shift["value_px"], "std": shift["std_px"],
            "true": lens_shift(true["k1"], true["k2"], [[0.0, 0.0], [0.0, 0.0]], shift["radius_px"],
                               shift["focal_px"])["value_px"]}


def spin_hidden(content: dict) -> bool:
    """Whether a run's (``discover.json``'s) recording is a ball, whose spin video does not see."""
    return (content.get("truth_motion") or {}).get("shape") == "sphere"


def ball_lift(content: dict) -> dict | None:
    """A run's (``discover.json``'s ``content``) ball lift in its final model against the engine's,
    as the video measures it: ``{"fitted", "std", "true", "angle_deg", "direction_deg",
    "across_velocity"}``. The first three are the size of the lift vector ``C_L ω``'s part across
    the direction the run's covariance knows least (:func:`torchfit.discover_video.least_seen`,
    about the flight's: its angle to the fitted initial velocity is ``direction_deg``), its
    standard error and the truth's part across that same direction, rad/s; ``angle_deg`` the
    angle between the fitted and the true part. This is the count since the thirty-sixth session
    (a rule fixed before fresh sets 12-15 were made, HISTORY.md). ``across_velocity`` holds the
    count before it, each vector's part across its own initial velocity (``fitted``, ``std``,
    ``true``, ``angle_deg``), which takes in the error of the direction the video does not see,
    14-19° from the velocity. None unless the final model holds a ball's lift (``ball_lift``) and
    the engine hid one."""
    fitted, truth = content["models"][-1].get("ball_lift"), content.get("truth_motion")
    lift = (content.get("truth_effects") or {}).get("magnus")
    if not fitted or not truth or not lift:
        return None
    value, covariance = np.asarray(fitted["value"], dtype=float), fitted["covariance"]
    true_vector = lift["lift_coefficient"] * np.asarray(truth["angular_velocity"], dtype=float)

    def compared(fitted_direction, true_direction) -> dict:
        size, std = lift_across(value, fitted_direction, covariance)
        a, b = across_velocity(value, fitted_direction), across_velocity(true_vector, true_direction)
        cosine = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-300)
        return {"fitted": size, "std": std, "true": float(np.linalg.norm(b)),
                "angle_deg": math.degrees(math.acos(min(max(cosine, -1.0), 1.0)))}

    direction = least_seen(covariance)
    return compared(direction, direction) | {"direction_deg": angle_to_line(direction, fitted["velocity"]),
                                             "across_velocity": compared(fitted["velocity"], truth["velocity"])}


def _without_third(score: dict) -> float | None:
    """A score's ΔBIC without its weakest third of the frames (recomputed from its per-frame
    evidence for runs from before the rule; None where neither is stored)."""
    if "delta_bic_without_block" in score:
        return score["delta_bic_without_block"]
    if "unit_delta_chi2" in score:
        return without_weakest_block(score["unit_delta_chi2"], score["delta_bic"], VIDEO_SELECTION.evidence_blocks)[0]
    return None


def table(rows: list[dict]) -> str:
    lines = ["| recording | hidden | verdict | right | baseline IoU (fitted / held-out) | held-out px before -> after "
             "| fitted vs true | needed to pass (true) | largest ΔBIC, round one (without its weakest third) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        # the true size as a departure from the effect's null value (a clock factor 0.975 is 0.025)
        truth = {p: np.abs(np.asarray(v) - np.asarray(EFFECTS[e].null_params[p])).tolist()
                 for e, values in r.get("truth_effects", {}).items() for p, v in values.items()}
        visible = "; ".join(f"{p} {_fmt(v)}" + (f" ({_fmt(truth[p])})" if truth.get(p) is not None else "")
                            for e, limits in r.get("detectable_above", {}).items() for p, v in limits.items()
                            if not (e == "magnus" and r.get("spin_hidden")))
        if "magnus" in r.get("detectable_above", {}) and r.get("spin_hidden"):
            visible = "; ".join(filter(None, (visible, "magnus: a ball's C_L ω, no single size")))
        fitted = "; ".join(f"{p} {_fmt(v['fitted'])} ± {_fmt(v['std'])} (true {_fmt(v['true'])}"
                           + (f", {v['angle_deg']:.0f}° apart)" if "angle_deg" in v else ")")
                           for e in r["params"].values() for p, v in e.items())
        verdict = ", ".join(r["verdict"]) or ("indistinguishable: " + " / ".join(r["indistinguishable"][0])
                                               if r["indistinguishable"] else "none")
        if r.get("verdict_withheld"):
            verdict = f"withheld (poor fit): {', '.join(r['verdict_withheld'])}"
        top, top_bic, top_thirds = r["top_delta_bic"]
        without = f" ({top_thirds:.1f})" if top_thirds is not None else ""
        # run before the thirds rule (†), or with an earlier edge nuisance than EDGE_FORM (‡)
        mark = ("" if r.get("thirds_rule") else " †") + ("" if _current_edge(r) else " ‡")
        lines.append(f"| {r['recording']}{mark} | {', '.join(r['truth']) or 'nothing'} | {verdict} | "
                     f"{_right(r)} | {r['iou_baseline']['mean_fitted']:.3f} / "
                     f"{r['iou_baseline']['mean_heldout']:.3f} | {r['heldout_px_before']:.2f} -> "
                     f"{r['heldout_px_after']:.2f} | {fitted} | {visible} | {top} {top_bic:.1f}{without} |")
    return "\n".join(lines)


# The coefficients the issue asks to be within 25 % of the engine's
# (a ball's lift as the size of its lift vector's part across the direction the video sees least,
# rad/s: ball_lift)
COEFFICIENTS = ("drag_coefficient", "lift_coefficient", "lift_across")


def halved(r: dict) -> bool:
    """Whether a row's held-out error after its named effects is at most half of the baseline's."""
    return r["heldout_px_after"] <= 0.5 * r["heldout_px_before"]


def _add_counts(total: dict, counts: dict) -> None:
    """Add :func:`score`'s ``counts`` of one set into ``total`` (pairs summed, names joined)."""
    for key, value in counts.items():
        total[key] = total.get(key, []) + value if key == "wrong_names" else \
            [a + b for a, b in zip(total.get(key, [0, 0]), value)]


def score(rows: list[dict]) -> dict:
    """The issue's targets counted over ``rows`` (:func:`row`): right verdicts on effect cases,
    quiet controls, recordings with a name that is not hidden, held-out error at least halved
    where the right effect was named, drag and lift coefficients within 25 % of the truth, and
    effect cases concealed as the issue defines it (baseline mean IoU >= 0.9 on the fitted frames;
    a control hides nothing to conceal)."""
    effect = [r for r in rows if r["truth"]]
    controls = [r for r in rows if not r["truth"]]
    named = [r for r in effect if r["right"]]
    coefficients = [(p, v["fitted"], v["true"]) for r in named for e in r["params"].values()
                    for p, v in e.items() if p in COEFFICIENTS]
    return {
        "effect_right": [len(named), len(effect)],
        "controls_quiet": [sum(r["right"] for r in controls), len(controls)],
        "wrong_names": sorted(r["recording"] for r in rows if set(r["verdict"]) - set(r["truth"])),
        "heldout_halved": [sum(halved(r) for r in named), len(named)],
        "coefficients_within_25pc": [sum(abs(f - t) <= 0.25 * abs(t) for _, f, t in coefficients), len(coefficients)],
        "concealed": [sum(r["concealed"] for r in effect), len(effect)],
    }


def score_line(counts: dict) -> str:
    """One line of the table's score (:func:`score`)."""
    def part(pair):
        return f"{pair[0]} of {pair[1]}"
    return (f"Right verdict on {part(counts['effect_right'])} effect cases; controls quiet "
            f"{part(counts['controls_quiet'])}; a name not hidden on "
            f"{', '.join(counts['wrong_names']) or 'no recording'}; held-out error at least halved on "
            f"{part(counts['heldout_halved'])} right names; drag and lift coefficients within 25 % on "
            f"{part(counts['coefficients_within_25pc'])}; effect cases concealed (baseline IoU >= 0.9) "
            f"{part(counts['concealed'])}.")


# fresh sets 3 and 4 were made and run on 2026-11-26 (sixth session), fresh set 5 in the tenth, once
# each, with no rule that decides a verdict changed after: the sets no choice has seen
SETS = {"first": "concealed", "fresh 1": "concealed_fresh1", "fresh 2": "concealed_fresh2",
        "fresh 3": "concealed_fresh3", "fresh 4": "concealed_fresh4", "fresh 5": "concealed_fresh5",
        "fresh 6": "concealed_fresh6", "fresh 7": "concealed_fresh7"}
# the exact masks' own edge term of the noise floor (calibrate_noise.py --true-masks: with the
# refits' exact moments, 2026-11-26, the rule gives 0.01 px; with the soft render's moments it gave
# 0.03 px, whose runs are kept as a row of their own); the exact-mask runs at EDGE_PX (0.1, the
# segmentation's) are the stored default ones
EXACT_EDGE_PX = 0.01
EXACT_EDGES = (0.03, EXACT_EDGE_PX)  # the exact masks' rows below their default one, sharpest last


def edge_suffix(edge_px: float | str) -> str:
    """A results folder's suffix for runs whose noise floor has the edge term ``edge_px``
    (none for the default ``"auto"``, ``EDGE_PX`` at 640 x 480: the stored default runs)."""
    return "" if edge_px == "auto" else f"_edge{edge_px:g}"


def edge_arg(text: str) -> float | str:
    """``--edge-px``: ``auto`` or a non-negative edge accuracy in pixels (:func:`edge_setting`)."""
    try:
        return edge_setting(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


# each kind of masks' results folder suffix
MASKS = {"segmented": "", "exact": "_true_masks"} | {f"exact, floor {edge:g} px": "_true_masks" + edge_suffix(edge)
                                                       for edge in EXACT_EDGES}


def limit_ratio(r: dict) -> float | None:
    """A recording's hidden effect against what its clip can show, by the run's own account: the
    true parameter's departure from its null over that parameter's detection limit in the run
    (``detectable_above``, what discover reports as "what this clip cannot rule out"; above 1 the
    clip could show it). ``r`` is the recording's :func:`row`: from a ``--true-masks`` run, the
    limit of the engine's exact masks; from a segmented run, the video's. None unless exactly one
    effect with one scalar parameter is hidden (a drag or lift coefficient, a clock): for effects
    of several numbers (a lens's k1 and k2, an offset) one number per parameter does not say
    whether their combination would pass (and runs before 2026-11-26's eighth session stored
    marginal limits, about three times too large for k1 and k2)."""
    if len(r["truth"]) != 1:
        return None
    (effect,) = r["truth"]
    if effect == "magnus" and r.get("spin_hidden"):  # a ball's lift is a vector C_L ω: three numbers
        return None
    limits, truth = r["detectable_above"].get(effect, {}), r["truth_effects"][effect]
    if len(limits) != 1 or len(truth) != 1:
        return None
    (pname, limit), = limits.items()
    true, null = truth[pname], EFFECTS[effect].null_params[pname]
    if isinstance(limit, list) or isinstance(true, list) or limit is None:
        return None
    return abs(true - null) / limit if limit > 0 else math.inf


def below_limit(r: dict) -> bool:
    """Whether a recording's hidden effect, not named, is below what its clip can show by the
    run's own account (:func:`limit_ratio` below 1; never for effects of several numbers)."""
    if r["right"]:
        return False
    ratio = limit_ratio(r)
    return ratio is not None and ratio < 1


# How a recording's run ended, from the best to the worst (:func:`outcome`)
OUTCOMES = ("named right", "indistinguishable, the truth among them", "nothing named, below its own limit",
            "nothing named, not excused by its own limit", "withheld (poor fit)", "a wrong name")


def outcome(r: dict) -> str:
    """One of ``OUTCOMES`` for an effect case's :func:`row` (a control's is "named right" when
    quiet, "a wrong name" otherwise). Only "named right" meets the issue's target; the next two
    are honest answers that name nothing: a tie reported between look-alikes one of which is
    hidden, and a miss that the run itself says the clip could not show (its reported detection
    limit above the truth, :func:`below_limit`). The last three are failures; the first of them
    takes a truth above its limit and an effect of several numbers (a lens, an offset), which
    gets no scalar limit (:func:`limit_ratio`)."""
    if r["right"]:
        return OUTCOMES[0]
    if set(r["verdict"]) - set(r["truth"]):
        return OUTCOMES[5]
    if r.get("verdict_withheld"):
        return OUTCOMES[4]
    if any(set(r["truth"]) & set(group) for group in r["indistinguishable"]):
        return OUTCOMES[1]
    return OUTCOMES[2] if below_limit(r) else OUTCOMES[3]


def _segmented_runs(root: Path, suffix: str) -> dict:
    """``{set label: {recording: row}}`` of every stored segmented set (``suffix``: a variant's)."""
    return {label: {r["recording"]: r for r in json.loads(file.read_text())}
            for label, name in SETS.items() if (file := root / f"{name}{suffix}" / "summary.json").exists()}


def outcomes(root: Path = OUT.parent, suffix: str = "", runs: dict | None = None) -> str:
    """How each set's effect cases ended on the segmented video (``suffix``: a variant's results,
    e.g. ``_crf4``; or ``runs``, ``{set label: {recording: row}}``, given), a column per
    :data:`OUTCOMES`, each but the first with its recordings."""
    lines = ["| set | " + " | ".join(OUTCOMES) + " |", "|---" * (len(OUTCOMES) + 1) + "|"]
    totals = [0] * len(OUTCOMES)
    for label, rows in (runs if runs is not None else _segmented_runs(root, suffix)).items():
        ended: dict = {kind: [] for kind in OUTCOMES}
        for r in rows.values():
            if r["truth"]:
                ended[outcome(r)].append(r["recording"])
        cells = [str(len(v)) + (f" ({', '.join(v)})" if i and v else "") for i, v in enumerate(ended.values())]
        totals = [t + len(v) for t, v in zip(totals, ended.values())]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("| **all** | " + " | ".join(f"**{t}**" for t in totals) + " |")
    return "\n".join(lines)


# Each outcome's word in the verdict grid (:func:`verdict_grid`), the failures in capitals
GRID_WORDS = dict(zip(OUTCOMES, ("right", "tie", "below limit", "MISSED", "WITHHELD", "WRONG")))


def grid_word(r: dict) -> str:
    """A recording's :func:`row` in a word: its :func:`outcome`'s (:data:`GRID_WORDS`), or a
    control's "quiet" or "ALARM"."""
    return GRID_WORDS[outcome(r)] if r["truth"] else ("quiet" if r["right"] else "ALARM")


def verdict_grid(root: Path = OUT.parent, suffix: str = "", runs: dict | None = None) -> str:
    """Every recording against every set on the segmented video (``suffix``: a variant's
    results; or ``runs`` given, as for :func:`outcomes`), each cell its :func:`outcome` in a word
    (:data:`GRID_WORDS`; a control's "quiet" or "ALARM") and the names discover gave, from the
    stored runs (no fitting)."""
    runs = runs if runs is not None else _segmented_runs(root, suffix)
    names = sorted({n for rows in runs.values() for n in rows}, key=lambda n: (n.startswith("control"), n))
    lines = ["| recording | hidden | " + " | ".join(runs) + " |", "|---" * (len(runs) + 2) + "|"]
    for name in names:
        cells = []
        for rows in runs.values():
            r = rows.get(name)
            if r is None:
                cells.append("")
                continue
            word = grid_word(r)
            said = ", ".join(r["verdict"] or r.get("verdict_withheld") or (r["indistinguishable"] or [[]])[0])
            cells.append(word + (f": {said}" if said and word != "right" else ""))
        hidden = next((", ".join(r["truth"]) for rows in runs.values() if (r := rows.get(name))), "")
        lines.append(f"| {name} | {hidden or 'nothing'} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def scoreboard(root: Path = OUT.parent) -> str:
    """The targets per set and over all sets, on the segmented video and on the exact masks (with
    the segmentation's noise floor and with lower ones, ``EXACT_EDGES``), and again
    over only the recordings whose hidden effect is above its exact-mask detection limit
    (:func:`below_limit` of the exact masks' run; from a recording's run at the exact masks' own floor where there
    is one, else from its run at the segmentation's); from the stored summary.json of each run
    (no fitting)."""
    lines = ["| set | masks | right | controls quiet | wrong names | held-out halved | coefficients within 25 % "
             "| effects concealed (baseline IoU ≥ 0.9) | right, effect above its exact-mask limit |",
             "|---|---|---|---|---|---|---|---|---|"]
    totals: dict = {}
    for label, name in SETS.items():
        exact: dict = {}
        for kind in [k for k in MASKS if k != "segmented"]:  # the sharper floor's row wins
            exact_file = root / f"{name}{MASKS[kind]}" / "summary.json"
            if exact_file.exists():
                exact |= {r["recording"]: r for r in json.loads(exact_file.read_text())}
        below = sorted(n for n, r in exact.items() if below_limit(r))
        for masks, folder in ((kind, name + suffix) for kind, suffix in MASKS.items()):
            file = root / folder / "summary.json"
            if not file.exists():
                continue
            rows = json.loads(file.read_text())
            counts = score(rows)
            above = [r for r in rows if r["truth"] and r["recording"] not in below and r["recording"] in exact]
            counts["above_limit"] = [sum(r["right"] for r in above), len(above)]
            _add_counts(totals.setdefault(masks, {}), counts)
            lines.append(_board_row(label, masks, counts, _concealed_and_above(counts)))
        if below:
            lines.append(f"| {label} | below the exact-mask limit | {', '.join(below)} | | | | | | |")
    for masks, counts in totals.items():
        lines.append(_board_row("**all**", masks, counts, _concealed_and_above(counts)))
    return "\n".join(lines)


def _concealed_and_above(counts: dict) -> str:
    """The scoreboard's last two cells: effect cases concealed, right ones above their limit."""
    return " | ".join(f"{a} of {b}" for a, b in (counts["concealed"], counts["above_limit"]))


def _rounds(content: dict) -> dict:
    """A discover.json's candidate scores by round: ``{base effects (tuple): {effect: score}}``."""
    rounds: dict = {}
    for effect, scores in content["effects"].items():
        for sc in scores:
            rounds.setdefault(tuple(sc["base"]), {})[effect] = sc
    return rounds


def side_by_side(suffix: str, label: str, root: Path = OUT.parent, masks: tuple[str, ...] = ("segmented",),
                 column: str = "run", base: str = "", base_label: str = "default") -> str:
    """Every stored set as run by default and as run with a variant (its folders end in ``suffix``:
    ``_chroma0.75`` for ``--chroma-weight 0.75``, ``_with_rolling_shutter`` for ``--with
    rolling_shutter``), over the recordings run both ways: the score of each set and of all, and
    every recording whose verdict or held-out halving differs. ``label`` names the variant's rows,
    ``column`` the column that holds ``default`` or ``label``; ``masks``: "segmented", "exact" (from
    the stored summary.json files under ``root``; no fitting). ``base``: the suffix of the runs
    compared against (another variant's, named ``base_label``), the default's if empty."""
    lines = [f"| set | masks | {column} | right | controls quiet | wrong names | held-out halved "
             "| coefficients within 25 % | recordings run both ways |", "|---|---|---|---|---|---|---|---|---|"]
    changed = [f"| set | masks | recording | hidden | verdict, {base_label} | verdict, {label} "
               f"| held-out px after, {base_label} / {label} |", "|---|---|---|---|---|---|---|"]
    totals: dict = {}
    run_both = dict.fromkeys(masks, 0)
    for name_label, name in SETS.items():
        for kind in masks:
            folder = name + MASKS[kind]
            pair = [root / f"{folder}{base}" / "summary.json", root / f"{folder}{suffix}" / "summary.json"]
            if not all(f.exists() for f in pair):
                continue
            rows = [{r["recording"]: r for r in json.loads(f.read_text())} for f in pair]
            common = sorted(set(rows[0]) & set(rows[1]))
            for variant, by_name in zip((base_label, label), rows):
                counts = score([by_name[n] for n in common])
                _add_counts(totals.setdefault((kind, variant), {}), counts)
                lines.append(_board_row(name_label, f"{kind} | {variant}", counts, str(len(common))))
            run_both[kind] += len(common)
            for n in common:
                a, b = rows[0][n], rows[1][n]
                if _verdict(a) != _verdict(b) or (a["right"] and halved(a)) != (b["right"] and halved(b)):
                    changed.append(f"| {name_label} | {kind} | {n} | {', '.join(a['truth']) or 'nothing'} "
                                   f"| {_verdict(a)} ({_right(a)}) | {_verdict(b)} ({_right(b)}) "
                                   f"| {a['heldout_px_after']:.2f} / {b['heldout_px_after']:.2f} |")
    for (kind, variant), counts in totals.items():
        lines.append(_board_row("**all**", f"{kind} | {variant}", counts, str(run_both[kind])))
    return "\n".join(lines) + "\n\nVerdict or held-out halving differs:\n\n" + "\n".join(changed)


def candidate_rounds(name: str, root: Path = OUT.parent) -> str:
    """Every round of every ``--with name`` run (all sets, segmented and exact) in which ``name``
    lowered the BIC by more than the threshold: its ΔBIC, the tests it failed, and the round's
    winner (the strongest candidate that passed) with its ΔBIC. From the stored discover.json
    files (no fitting)."""
    threshold = VIDEO_SELECTION.min_delta_bic
    lines = [f"| set | masks | recording | hidden | round (after) | {name} ΔBIC | failed | strongest passing "
             "| verdict |", "|---|---|---|---|---|---|---|---|---|"]
    for label, set_name in SETS.items():
        for kind, suffix in MASKS.items():
            for file in sorted((root / f"{set_name}{suffix}_with_{name}").glob("*/discover.json")):
                content = json.loads(file.read_text())
                for base, scores in _rounds(content).items():
                    mine = scores.get(name)
                    if mine is None or mine["delta_bic"] <= threshold:
                        continue
                    passing = sorted(((sc["delta_bic"], e) for e, sc in scores.items() if sc["passes"]), reverse=True)
                    best = f"{passing[0][1]} {passing[0][0]:.1f}" if passing else "none"
                    lines.append(f"| {label} | {kind} | {file.parent.name} | {', '.join(content.get('truth_effects') or {}) or 'nothing'} "
                                 f"| {'+'.join(base) or 'baseline'} | {mine['delta_bic']:.1f} | {', '.join(mine['fails']) or 'none'} "
                                 f"| {best} | {', '.join(content['verdict']) or 'none'} |")
    return "\n".join(lines)


RULES = ("unphysical", "evidence_spread", "heldout", "wald")  # the tests besides the ΔBIC threshold


def rule_tally(root: Path = OUT.parent, masks_kinds: dict | None = None) -> dict:
    """What each test alone kept out, over every stored set: the candidates that pass the ΔBIC
    threshold and fail only that test, and would have changed their round (no candidate passed
    it, or theirs is within the look-alike margin of the winner's ΔBIC or above it).

    Returns ``{masks: {rule: {"right": [...], "wrong": [...]}}}``, each entry
    ``"set/recording: effect (after base) ΔBIC x"``; ``right`` when the effect is hidden there.
    From the stored discover.json files (no fitting). Counterfactual for that round only: what
    later rounds would have done is not known. ``masks_kinds``: ``{label: folder suffix}`` in
    place of ``MASKS`` (e.g. a variant's segmented runs)."""
    margin = VIDEO_SELECTION.lookalike_margin
    out: dict = {}
    for label, name in SETS.items():
        for masks, folder in ((kind, name + suffix) for kind, suffix in (masks_kinds or MASKS).items()):
            tally = out.setdefault(masks, {rule: {"right": [], "wrong": []} for rule in RULES})
            for file in sorted((root / folder).glob("*/discover.json")):
                content = json.loads(file.read_text())
                truth = set(content.get("truth_effects") or {})
                for base, scores in _rounds(content).items():
                    passing = [sc["delta_bic"] for sc in scores.values() if sc["passes"]]
                    best = max(passing, default=None)
                    for effect, sc in scores.items():
                        if len(sc["fails"]) != 1 or sc["fails"][0] not in RULES:
                            continue
                        if best is not None and sc["delta_bic"] < best - margin:
                            continue
                        after = f" after {'+'.join(base)}" if base else ""
                        entry = f"{label}/{file.parent.name}: {effect}{after} ΔBIC {sc['delta_bic']:.1f}"
                        tally[sc["fails"][0]]["right" if effect in truth else "wrong"].append(entry)
    return out


def rules_text(tally: dict) -> str:
    def cell(entries):
        return f"{len(entries)}: " + "; ".join(entries) if entries else "0"

    lines = ["| masks | test | right names it alone kept out | wrong names it alone kept out |", "|---|---|---|---|"]
    for masks, rules in tally.items():
        for rule, kept in rules.items():
            lines.append(f"| {masks} | {rule} | {cell(kept['right'])} | {cell(kept['wrong'])} |")
    return "\n".join(lines)


def _board_row(label: str, masks: str, counts: dict, last: str) -> str:
    """A scoreboard row of :func:`score`'s ``counts``, its last cell (or cells) ``last``."""
    def part(pair):
        return f"{pair[0]} of {pair[1]}"
    return (f"| {label} | {masks} | {part(counts['effect_right'])} | {part(counts['controls_quiet'])} | "
            f"{', '.join(counts['wrong_names']) or 'none'} | {part(counts['heldout_halved'])} | "
            f"{part(counts['coefficients_within_25pc'])} | {last} |")


def _current_edge(r: dict) -> bool:
    """Whether the row ran with today's edge nuisance (discover.json names its form; earlier runs did not)."""
    return r.get("edge_px", {}).get("form") == EDGE_FORM


def _verdict(r: dict) -> str:
    return ", ".join(r["verdict"]) or ("indistinguishable" if r["indistinguishable"] else "none")


def _strongest(r: dict) -> str:
    name, bic, third = r["top_delta_bic"]
    return f"{name} {bic:.1f}" + (f" ({third:.1f})" if third is not None else "")


def _right(r: dict) -> str:
    """'yes', or 'NO' with what went wrong when the hidden effect was named with others."""
    if r["right"]:
        return "yes"
    extra = [v for v in r["verdict"] if v not in r["truth"]]
    return f"NO (also named {', '.join(extra)})" if r["truth"] and r["verdict"][:1] == r["truth"][:1] else "NO"


def _fmt(value) -> str:
    if isinstance(value, list):
        return "(" + ", ".join(f"{v:.3g}" for v in value) + ")"
    return f"{value:.3g}"


def rebuild(out: Path = OUT, recordings: Path = RECORDINGS) -> str:
    """summary.json and table.md from every discover.json under ``out`` (no fitting: rows of other
    runs and earlier ones are read back the same way); returns the table. A row that needs its
    recording (a centre-of-mass offset, compared modulo the shape's symmetries) where that
    recording is no longer in ``recordings`` (a set partly made again) keeps the row summary.json
    already holds for it; without one it stops, naming the recording."""
    stored_path = out / "summary.json"
    stored = {r["recording"]: r for r in json.loads(stored_path.read_text())} if stored_path.exists() else {}
    rows = []
    for f in sorted(out.glob("*/discover.json")):
        name, content = f.parent.name, json.loads(f.read_text())
        if "com_offset" in content.get("truth_effects", {}) and not (recordings / name / "truth.json").exists():
            if name not in stored:
                sys.exit(f"{recordings / name} is missing and {stored_path} holds no row for it: "
                         "make the recording again (make_concealed.py) to rebuild the table")
            print(f"{recordings / name} is missing: its row is the one {stored_path} holds", file=sys.stderr)
            rows.append(stored[name])
        else:
            rows.append(row(name, content, recordings))
    text = table(rows) + "\n\n" + score_line(score(rows))
    (out / "summary.json").write_text(json.dumps(rows, indent=1))
    (out / "table.md").write_text(text + "\n")
    return text


def compare(out: Path, revision: str) -> str:
    """Markdown rows of each recording rerun with today's edge nuisance (``EDGE_FORM``) against its
    row in ``out``'s summary.json at git ``revision``: verdict, round one's strongest candidate,
    held-out error after, and the fitted edge terms."""
    root = HERE.parents[1]
    path = (out / "summary.json").relative_to(root).as_posix()
    before = {r["recording"]: r for r in json.loads(subprocess.check_output(["git", "show", f"{revision}:{path}"],
                                                                            cwd=root))}
    lines = ["| recording | verdict before -> now | right | strongest, round one (without weakest third) "
             "| held-out px after | edge b0, ends minus sides (px) |", "|---|---|---|---|---|---|"]
    for r in json.loads((out / "summary.json").read_text()):
        old = before.get(r["recording"])
        if not _current_edge(r) or old is None:
            continue
        edge = r["edge_px"]
        lines.append(f"| {r['recording']} | {_verdict(old)} -> {_verdict(r)} | {_right(old)} -> {_right(r)} | "
                     f"{_strongest(old)} -> {_strongest(r)} | {old['heldout_px_after']:.2f} -> {r['heldout_px_after']:.2f} | "
                     f"{edge['value']:+.2f} ± {edge['std']:.2f}, {edge['ends_minus_sides']:+.2f} ± "
                     f"{edge['ends_minus_sides_std']:.2f} |")
    return "\n".join(lines)


def _round_gains(content: dict) -> dict:
    """``(round, candidate) -> (ΔBIC, held-out gain %)`` of every candidate scored in a
    discover.json's ``effects``; a round is named by the effects it adds to."""
    return {("+".join(score["base"]) or "baseline", name): (score["delta_bic"], 100 * score["heldout_gain"])
            for name, scores in content["effects"].items() for score in scores}


def heldout_moves(out: Path, revision: str, points: float = 5.0) -> str:
    """Markdown rows of the candidates (every round's) whose held-out gain moved by
    at least ``points`` percentage points between git ``revision``'s discover.json and today's,
    and how many such candidates were compared."""
    root = HERE.parents[1]
    lines = ["| recording | round: candidate | ΔBIC before -> now | held-out gain before -> now |", "|---|---|---|---|"]
    compared = 0
    for path in sorted(out.glob("*/discover.json")):
        try:
            old = json.loads(subprocess.check_output(["git", "show", f"{revision}:{path.relative_to(root).as_posix()}"],
                                                     cwd=root, stderr=subprocess.DEVNULL))
        except subprocess.CalledProcessError:
            continue
        before, now = _round_gains(old), _round_gains(json.loads(path.read_text()))
        for key in before.keys() & now.keys():
            compared += 1
            if abs(before[key][1] - now[key][1]) >= points:
                lines.append(f"| {path.parent.name} | {key[0]}: {key[1]} | {before[key][0]:.1f} -> {now[key][0]:.1f} | "
                             f"{before[key][1]:+.0f} % -> {now[key][1]:+.0f} % |")
    return "\n".join(lines + [f"\n{len(lines) - 2} of {compared} candidates' held-out gains moved by >= {points:g} points"])


def results_name(settings: str, *, fresh: int = 0, true_masks: bool = False, shipped: bool = False,
                 shutter: bool = False, chroma_weight: float | None = None, variant: str = "",
                 read_as: str | None = None, declare_lens: bool = False) -> str:
    """A run's results folder name under results/: the set (``concealed[_freshK]``, the
    rolling-shutter set's ``rolling_shutter``, or ``shipped``), the masks, then ``settings``, the
    suffixes of the run's settings (empty for the settings of the day a set's first runs were made),
    and the set's variant (``_sharp``, ``_crf4``...). The shipped recordings' runs have one folder."""
    masks = MASKS["exact" if true_masks else "segmented"]
    if shipped:
        return "shipped"
    if shutter:
        return "rolling_shutter" + masks + settings
    return (OUT.name + (f"_fresh{fresh}" if fresh else "") + masks
            + (f"_chroma{chroma_weight:g}" if chroma_weight is not None else "")
            + settings + variant + (f"_read_{read_as}" if read_as else "") + ("_lensdeclared" if declare_lens else ""))


def main(names: list[str], *, true_masks: bool = False, shipped: bool = False, fresh: int = 0,
         table_only: bool = False, against: str | None = None, chroma_weight: float | None = None,
         shutter: bool = False, extra: tuple[str, ...] = (), edge_px: float | str = "auto", sharp: bool = False,
         crf: int | None = None, albedo_passes: int | None = None, transfer: str | None = None,
         read_as: str | None = None, exposure: bool = False, exposure_fraction: float | None = None,
         coverage_near_px: int | None = None, coverage_clip: bool | None = None, fit_exposure: bool = False,
         point_spread: tuple[float, float] | None = None, baseline_starts: int = 1,
         exposure_taps: int | None = None, coverage_band: str | None = None,
         shading_fit: str | None = None, well_posed_grey: float | None = None,
         interior_shading: bool | None = None, speed_noise: bool = False, heldout_margin: float | None = None, robust: float | None = None, declare_lens: bool = False,
         backcast: bool = False,
         search_final: int | None = None, scale: int = 1, fps_scale: Fraction = Fraction(1),
         jump_sigmas: float | None = JUMP_SIGMAS, jump_one_at_a_time: bool = False,
         jump_neighbours: int = 0, jump_refined: bool = False, shuffle_error: int | None = None) -> None:
    # the set, or its copy without motion blur, at another H.264 quality, through a camera curve or
    # through a camera of more pixels
    recordings = fresh_folder(fresh, sharp, crf, transfer, scale, fps_scale)
    variant = recordings.name.removeprefix(fresh_folder(fresh).name)
    settings = (segmentation_suffix(albedo_passes, exposure, exposure_fraction, coverage_near_px,
                                    coverage_clip, fit_exposure, point_spread, exposure_taps,
                                    coverage_band, shading_fit, well_posed_grey, interior_shading)
                + "".join(f"_with_{name}" for name in extra)
                + (f"_starts{baseline_starts}" if baseline_starts > 1 else "")
                + ("_speednoise" if speed_noise else "")
                + heldout_suffix(heldout_margin) + robust_suffix(robust)
                + backcast_suffix(backcast) + edge_suffix(edge_px)
                + final_suffix(search_final) + jump_suffix(jump_sigmas, jump_one_at_a_time, jump_neighbours,
                                                                      jump_refined)
                + (f"_errshuffled{shuffle_error}" if shuffle_error is not None else ""))
    out = OUT.with_name(results_name(settings, fresh=fresh, true_masks=true_masks, shipped=shipped, shutter=shutter,
                                     chroma_weight=chroma_weight, variant=variant, read_as=read_as,
                                     declare_lens=declare_lens))
    if shutter:  # the rolling-shutter set, with rolling_shutter as one more candidate
        recordings, extra = RECORDINGS.with_name("recordings_shutter"), ("rolling_shutter",)
    if table_only:
        return print(rebuild(out, recordings))
    if against:
        rebuild(out, recordings)
        return print(compare(out, against) + "\n\n" + heldout_moves(out, against))
    if shipped:
        folders = [Path(torchfit.__file__).parent / "recordings" / n for n in names or SHIPPED]
    elif not recordings.exists():
        sys.exit(f"no recordings in {recordings}: run python experiments/discover/make_concealed.py"
                 + (f" --fresh {fresh}" if fresh else "") + (" --shutter" if shutter else "")
                 + (" --sharp" if sharp else "") + (f" --crf {crf}" if crf is not None else "")
                 + (f" --transfer {transfer}" if transfer else "") + (f" --scale {scale}" if scale != 1 else "")
                 + (f" --fps-scale {fps_scale}" if fps_scale != 1 else ""))
    else:
        folders = [recordings / n for n in names] if names else sorted(p for p in recordings.iterdir() if p.is_dir())
    for folder in folders:
        clock = time.perf_counter()
        print(f"== {folder.name}", flush=True)
        content = run_one(folder, out / folder.name, true_masks=true_masks, chroma_weight=chroma_weight,
                          candidates=CANDIDATES + tuple(extra), edge_px=edge_px, albedo_passes=albedo_passes,
                          transfer=read_as or transfer, exposure=exposure, exposure_fraction=exposure_fraction,
                          coverage_near_px=coverage_near_px, coverage_clip=coverage_clip, fit_exposure=fit_exposure,
                          point_spread=point_spread, baseline_starts=baseline_starts, exposure_taps=exposure_taps,
                          coverage_band=coverage_band, shading_fit=shading_fit, well_posed_grey=well_posed_grey,
                          interior_shading=interior_shading,
                          speed_noise=speed_noise,
                          heldout_margin=heldout_margin, robust=robust, declare_lens=declare_lens,
                          backcast=backcast, search_final=search_final, jump_sigmas=jump_sigmas,
                          jump_one_at_a_time=jump_one_at_a_time, jump_neighbours=jump_neighbours,
                          jump_refined=jump_refined, shuffle_error=shuffle_error)
        print(f"== {folder.name}: verdict {content['verdict']} (truth {list(content['truth_effects'])}), "
              f"{time.perf_counter() - clock:.0f} s", flush=True)
        summary = rebuild(out, recordings)  # after each recording, with what other runs have written meanwhile
    print(summary)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="recordings (default: all of the set)")
    ap.add_argument("--table", action="store_true", help="only rebuild the table from the outputs")
    ap.add_argument("--true-masks", action="store_true", help="MuJoCo's true masks instead of the segmentation")
    ap.add_argument("--shipped", action="store_true", help="the shipped recordings (hide nothing)")
    ap.add_argument("--fresh", type=int, default=0, metavar="K", help="fresh set K (make_concealed.py --fresh K)")
    ap.add_argument("--shutter", action="store_true",
                    help="the rolling-shutter set (make_concealed.py --shutter) with rolling_shutter as a candidate "
                         "(results/rolling_shutter[_true_masks]/)")
    ap.add_argument("--sharp", action="store_true",
                    help="the set remade without motion blur (make_concealed.py --sharp; results/..._sharp/)")
    ap.add_argument("--shuffle-error", type=int, default=None, metavar="SEED",
                    help="with --sharp --exposure: the exact masks' moments carrying the segmentation's own "
                         "per-frame error in a shuffled order (results/..._errshuffled<SEED>_sharp/)")
    ap.add_argument("--crf", type=int, default=None, metavar="C",
                    help="the set encoded at H.264 quality C (make_concealed.py --crf C; results/..._crf<C>/)")
    ap.add_argument("--scale", type=int, default=1, metavar="N",
                    help="the set filmed with N times the pixels along each side (make_concealed.py --scale N; "
                         "results/..._x<N>/)")
    ap.add_argument("--fps-scale", type=fps_factor, default=Fraction(1), metavar="N|1/N|P/Q",
                    help="the set filmed at this many times the frame rate (make_concealed.py --fps-scale F; "
                         "results/..._fps<N>/, ..._fps1by<N>/, ..._fps<P>by<Q>/)")
    ap.add_argument("--transfer", choices=("srgb", "bt709"), default=None,
                    help="the set stored through this camera curve (make_concealed.py --transfer T), segmented "
                         "with SegmentationSettings.transfer T (results/..._<T>/)")
    ap.add_argument("--read-as", choices=TRANSFERS, default=None,
                    help="with --transfer: segment as if the frames were stored through this curve instead "
                         "(results/..._<T>_read_<R>/)")
    ap.add_argument("--with", dest="extra", action="append", default=[], choices=sorted(set(VIDEO_EFFECTS) - set(CANDIDATES)),
                    help="one more candidate besides the defaults (repeatable; results/concealed..._with_<name>/)")
    ap.add_argument("--chroma-weight", type=float, metavar="W",
                    help="segment with this SegmentationSettings.chroma_weight (results/concealed..._chroma<W>/)")
    ap.add_argument("--albedo-passes", type=int, metavar="N",
                    help="segment with this SegmentationSettings.albedo_passes (results/concealed..._albedo<N>/)")
    ap.add_argument("--exposure", action="store_true",
                    help="compare the soft coverage with the silhouette averaged over the recording's exposure "
                         "(truth.json's render; results/concealed..._exposure/)")
    ap.add_argument("--coverage-near-px", type=lambda v: v if v == "auto" else int(v), metavar="N",
                    help="with --exposure: the soft coverage counted within N px of the mask instead of the "
                         "default auto, 4 steps in a 640 x 480 camera's units (SegmentationSettings.coverage_near_px; "
                         "results/concealed..._exposure_near<N>/)")
    ap.add_argument("--unclipped", action="store_true",
                    help="with --exposure: the soft coverage's moments without its clip to [0, 1] "
                         "(SegmentationSettings.coverage_clip off; results/concealed..._exposure..._unclipped/)")
    ap.add_argument("--motion-band", action="store_true",
                    help="with --exposure: the coverage's band swept half the frame's travel along the motion "
                         "(SegmentationSettings.coverage_band='motion'; results/concealed..._motionband/)")
    ap.add_argument("--linear-shading", action="store_true",
                    help="segment with the local-linear shading "
                         "(SegmentationSettings.shading_fit='linear'; results/concealed..._linshade/)")
    ap.add_argument("--well-posed-grey", type=float, metavar="G",
                    help="segment trusting the per-pixel fit where |B| sin(angle(A, B)) exceeds G grey levels "
                         "(SegmentationSettings.well_posed_grey; results/concealed..._grey<G>/)")
    ap.add_argument("--interior-shading", action="store_true",
                    help="segment with the shading also supported by the object's interior where the per-pixel "
                         "fit is not trusted (SegmentationSettings.interior_shading; results/concealed..._interior/)")
    ap.add_argument("--fit-exposure", action="store_true",
                    help="with --exposure: fit the exposure's fraction as a nuisance of every model, from the "
                         "recording's own or --exposure-fraction (results/concealed..._exposure..._fitted/)")
    ap.add_argument("--fit-point-spread", action="store_true",
                    help="with --exposure: fit the image's point spread (px^2 added to every silhouette's variance) "
                         "as a nuisance of every model, from 0 with no prior (results/concealed..._exposure..._spread/)")
    ap.add_argument("--point-spread-prior", type=float, nargs=2, metavar=("M", "S"),
                    help="with --exposure: fit the point spread from M px^2 with a Gaussian prior M ± S px^2 "
                         "(results/concealed..._exposure..._spread<M>pm<S>/)")
    ap.add_argument("--search-final", type=int, metavar="N",
                    help="the baseline search polishes up to N distinct minima instead of SearchSettings' "
                         "default (results/concealed..._final<N>/)")
    ap.add_argument("--baseline-starts", type=int, default=1, metavar="N",
                    help="the baseline's refit from the search's first N candidates, the lowest cost kept "
                         "(VideoProblem(baseline_starts=N); results/concealed..._starts<N>/)")
    ap.add_argument("--exposure-fraction", type=float, metavar="F",
                    help="with --exposure: this fraction of the frame interval instead of the recording's own, "
                         "as a user's guess would be (results/concealed..._exposure<F>/)")
    ap.add_argument("--exposure-taps", type=int, metavar="T",
                    help="with --exposure: the exposure as T sub-frames instead of the recording's own, 0 a "
                         "camera's, as a user who does not know the renderer gives it (results/concealed..._taps<T>/)")
    ap.add_argument("--speed-noise", action="store_true",
                    help="noise floors that grow with the silhouette's speed, by a share read from the data "
                         "(discover_video(speed_noise=True); results/concealed..._speednoise/)")
    ap.add_argument("--heldout-margin", type=float, metavar="M",
                    help="judge the held-out frames by their predictive deviance, which may rise by at most M "
                         "(SelectionSettings.heldout_margin; results/concealed..._heldout<M>/)")
    ap.add_argument("--robust", type=float, metavar="K",
                    help="the criterion takes Huber's loss at K noise units instead of squares "
                         "(VideoProblem(robust=K); results/concealed..._huber<K>/)")
    ap.add_argument("--backcast", action="store_true",
                    help="the held-out test also predicts the first quarter of the frames backward from the rest "
                         "and scores the mean of the two parts (discover_video(backcast=True); "
                         "results/concealed..._backcast/)")
    ap.add_argument("--jump-sigmas", type=float, default=JUMP_SIGMAS, metavar="S",
                    help=f"leave out frames that jump off their neighbours by more than S jitter sigmas "
                         f"(default {JUMP_SIGMAS:g}; results/concealed..._jump<S>/ otherwise)")
    ap.add_argument("--no-jump-test", action="store_true",
                    help="leave no frame out as a failed segmentation (discover_video(jump_sigmas=None); "
                         "results/concealed..._nojump/)")
    ap.add_argument("--jump-one-at-a-time", action="store_true",
                    help="the jump test leaves frames out worst first, taking the scores again after each, so a "
                         "failed frame takes no neighbour with it (discover_video(jump_one_at_a_time=True); "
                         "results/concealed..._1by1/)")
    ap.add_argument("--jump-neighbours", type=int, default=0, metavar="K",
                    help="the jump test also leaves out the K frames on either side of each frame it leaves out "
                         "(discover_video(jump_neighbours=K); results/concealed..._nb<K>/)")
    ap.add_argument("--jump-refined", action="store_true",
                    help="the jump test judged on the baseline refitted to every frame instead of on the search's "
                         "best (discover_video(jump_refined=True); results/concealed..._refj/)")
    ap.add_argument("--declare-lens", action="store_true",
                    help="the camera as calibrated, its lens distortion declared (truth.json camera_true): "
                         "a hidden lens is then known and the recording hides nothing (results/..._lensdeclared/)")
    ap.add_argument("--edge-px", type=edge_arg, default="auto", metavar="E",
                    help=f"the noise floor's edge term in pixels (default auto: {EDGE_PX:g} at 640 x 480, "
                         f"discover_video.edge_term; results/concealed..._edge<E>/)")
    ap.add_argument("--compare", metavar="REV", help="the rows rerun with today's edge nuisance against git REV's")
    ap.add_argument("--scoreboard", action="store_true",
                    help="the targets over every stored set, segmented and exact masks (results/scoreboard.md); "
                         "with --chroma-weight W the segmented sets at the default weight and at W side by side "
                         "(results/chroma<W>_side_by_side.md), with --albedo-passes N the same for that "
                         "segmentation (results/albedo<N>_side_by_side.md), with --crf C the segmented sets at crf 14 and at C "
                         "(results/crf<C>_side_by_side.md), with --with NAME the sets with and without that "
                         "candidate (results/with_<NAME>_side_by_side.md), with --edge-px E the exact masks' sets "
                         "at the default edge term and at E (results/edge<E>_side_by_side.md)")
    ap.add_argument("--rules", action="store_true",
                    help="what each test alone kept out over every stored set (results/rules.md)")
    args = ap.parse_args()
    # the point spread fitted: from 0 without a prior, or from M with the prior M ± S px^2
    point_spread = ((0.0, math.inf) if args.fit_point_spread
                    else tuple(args.point_spread_prior) if args.point_spread_prior else None)
    # the segmentation variant's results folder suffix (--albedo-passes, --exposure and their options)
    variant = (segmentation_suffix(args.albedo_passes, args.exposure, args.exposure_fraction, args.coverage_near_px,
                                   False if args.unclipped else None, args.fit_exposure, point_spread,
                                   args.exposure_taps, "motion" if args.motion_band else None,
                                   "linear" if args.linear_shading else None, args.well_posed_grey,
                                   True if args.interior_shading else None)
               if args.albedo_passes is not None or args.exposure or args.linear_shading
               or args.well_posed_grey is not None or args.interior_shading else "")
    variant += "_speednoise" if args.speed_noise else ""
    variant += heldout_suffix(args.heldout_margin) + robust_suffix(args.robust) + backcast_suffix(args.backcast)
    if not (math.isfinite(args.jump_sigmas) and args.jump_sigmas > 0):
        ap.error(f"--jump-sigmas needs a positive number of jitter standard deviations, got {args.jump_sigmas}")
    if args.no_jump_test and args.jump_sigmas != JUMP_SIGMAS:
        ap.error("--no-jump-test leaves no frame out: not with --jump-sigmas")
    if args.no_jump_test and args.jump_one_at_a_time:
        ap.error("--no-jump-test leaves no frame out: not with --jump-one-at-a-time")
    if args.jump_neighbours < 0:
        ap.error(f"--jump-neighbours needs a whole number of frames >= 0, got {args.jump_neighbours}")
    if args.no_jump_test and (args.jump_neighbours or args.jump_refined):
        ap.error("--no-jump-test leaves no frame out: not with --jump-neighbours or --jump-refined")
    jump_sigmas = None if args.no_jump_test else args.jump_sigmas
    variant += final_suffix(args.search_final) + jump_suffix(jump_sigmas, args.jump_one_at_a_time,
                                                             args.jump_neighbours, args.jump_refined)
    if args.robust is not None and not (math.isfinite(args.robust) and args.robust > 0):
        ap.error(f"--robust needs Huber's threshold in noise units, a positive number, got {args.robust}")
    if args.heldout_margin is not None and not args.heldout_margin >= 0:
        ap.error(f"--heldout-margin needs a deviance >= 0, got {args.heldout_margin}")
    if args.rules:  # with a variant: over its segmented runs
        text = rules_text(rule_tally(masks_kinds={f"segmented ({variant[1:]})": variant} if variant else None))
        (OUT.parent / f"rules{variant}.md").write_text(text + "\n")
        sys.exit(print(text))
    if args.scoreboard and (args.chroma_weight is not None or args.extra or args.edge_px != "auto"
                            or args.crf is not None or args.albedo_passes is not None or args.exposure
                            or args.linear_shading or args.well_posed_grey is not None or args.interior_shading
                            or args.speed_noise
                            or args.heldout_margin is not None
                            or args.robust is not None or args.backcast or args.search_final is not None):
        if variant:
            suffix = variant
            against = ("the exposure" if args.exposure_fraction is None
                       else f"an exposure of {args.exposure_fraction:g}") + (
                "" if args.exposure_taps is None else " as a camera's" if args.exposure_taps == 0
                else f" in {args.exposure_taps} sub-frames")
            path_parts = (([f"albedo passes {args.albedo_passes}"] if args.albedo_passes is not None else [])
                              + ([f"coverage against {against}"] if args.exposure else [])
                              + ([f"coverage within {args.coverage_near_px} px"]
                                 if args.coverage_near_px is not None else [])
                              + (["swept along the motion"] if args.motion_band else [])
                              + (["unclipped"] if args.unclipped else [])
                              + (["local-linear shading"] if args.linear_shading else [])
                              + ([f"the per-pixel fit trusted above {args.well_posed_grey:g} grey levels"]
                                 if args.well_posed_grey is not None else [])
                              + (["the shading supported by the interior"] if args.interior_shading else [])
                              + (["the exposure fitted"] if args.fit_exposure else [])
                              + ([] if point_spread is None else
                                 ["the point spread fitted" + ("" if math.isinf(point_spread[1]) else
                                                               f" (prior {point_spread[0]:g} ± {point_spread[1]:g} px²)")]))
            options = ((["noise floors growing with the speed"] if args.speed_noise else [])
                       + ([f"held-out deviance within {args.heldout_margin:g}"] if args.heldout_margin is not None
                          else [])
                       + ([f"Huber's loss at {args.robust:g}"] if args.robust is not None else [])
                       + (["the first quarter backcast as well"] if args.backcast else []))
            final = final_suffix(args.search_final)
            searched = [f"the search polishing up to {final.removeprefix('_final')} minima"] if final else []
            label = ", ".join(path_parts + options + searched)
            # an option on another path: against that path without it; the backcast or a final
            # asked for against the same runs without it (every other option, and the search, kept)
            core = variant.removesuffix(final)
            if final and args.search_final is not None:  # against the first runs' search
                path, base_options = core, options
            elif args.backcast:
                path, base_options = core.removesuffix(backcast_suffix(True)) + final, options[:-1] + searched
            else:
                path = (core.removesuffix(robust_suffix(args.robust)).removesuffix(heldout_suffix(args.heldout_margin))
                        .removesuffix("_speednoise") + final if options else "")
                base_options = searched
            base_label = ", ".join(path_parts + base_options)
            text = side_by_side(suffix, label, column="segmentation", base=path,
                                base_label=base_label if path else "default")
        elif args.crf is not None:
            suffix, label = f"_crf{args.crf}", f"crf {args.crf}"
            text = side_by_side(suffix, label, column="H.264 quality")
        elif args.chroma_weight is not None:
            suffix, label = f"_chroma{args.chroma_weight:g}", f"chroma {args.chroma_weight:g}"
            text = side_by_side(suffix, label, column="segmentation")
        elif args.edge_px != "auto":
            suffix, label = edge_suffix(args.edge_px), f"edge {args.edge_px:g} px"
            text = side_by_side(suffix, label, masks=("exact",), column="noise floor")
        else:
            suffix = "".join(f"_with_{name}" for name in args.extra)
            label = "with " + ", ".join(args.extra)
            text = side_by_side(suffix, label, masks=("segmented", "exact"), column="candidates")
            text += "".join(f"\n\nRounds where {name} lowered the BIC by more than the threshold:\n\n"
                            + candidate_rounds(name) for name in args.extra)
        if args.crf is not None:
            text += (f"\n\nHow the effect cases ended at crf 14 and at {label} (concealed.outcome):\n\n"
                     + outcomes() + "\n\n" + outcomes(suffix=suffix))
        (OUT.parent / f"{suffix[1:]}_side_by_side.md").write_text(text + "\n")
        sys.exit(print(text))
    if args.scoreboard:
        board = scoreboard() + ("\n\nHow the segmented video's effect cases ended (concealed.outcome: the "
                                "recordings of every column but the first named):\n\n" + outcomes()
                                + "\n\nEvery recording on the segmented video (concealed.verdict_grid):\n\n"
                                + verdict_grid())
        (OUT.parent / "scoreboard.md").write_text(board + "\n")
        sys.exit(print(board))
    if args.search_final is not None and args.search_final < 1:
        ap.error(f"--search-final needs at least one minimum, got {args.search_final}")
    if args.baseline_starts < 1:
        ap.error(f"--baseline-starts needs at least one candidate, got {args.baseline_starts}")
    if args.fresh < 0:
        ap.error(f"--fresh needs a set number K >= 1, got {args.fresh}")
    if args.coverage_near_px is not None:
        if not args.exposure:
            ap.error("--coverage-near-px needs --exposure (only the exposure reads the coverage)")
        try:  # the settings' own check of the band
            SegmentationSettings(coverage_near_px=args.coverage_near_px)
        except ValueError as err:
            ap.error(f"--coverage-near-px: {err}")
    if args.fit_exposure and not args.exposure:
        ap.error("--fit-exposure needs --exposure (the fraction it starts from)")
    if (args.fit_point_spread or args.point_spread_prior) and not args.exposure:
        ap.error("--fit-point-spread and --point-spread-prior need --exposure (the point spread is fitted to the "
                 "soft coverage)")
    if args.fit_point_spread and args.point_spread_prior:
        ap.error("--fit-point-spread fits the point spread without a prior: not with --point-spread-prior")
    if args.point_spread_prior and not (math.isfinite(args.point_spread_prior[0]) and args.point_spread_prior[1] > 0):
        ap.error(f"--point-spread-prior needs a finite mean and a positive spread, got {args.point_spread_prior}")
    if (args.unclipped or args.motion_band) and not args.exposure:
        ap.error("--unclipped and --motion-band need --exposure (only the exposure reads the coverage)")
    for flag, given in (("--linear-shading", args.linear_shading), ("--interior-shading", args.interior_shading)):
        if given and (args.true_masks or args.shipped or args.shutter):
            ap.error(f"{flag} is a segmentation setting: not with --true-masks, --shipped or --shutter")
    grey_ok = args.well_posed_grey is None or (math.isfinite(args.well_posed_grey) and args.well_posed_grey >= 0)
    if args.well_posed_grey is not None and (args.true_masks or args.shipped or args.shutter or not grey_ok):
        ap.error(f"--well-posed-grey is a segmentation setting, grey levels >= 0 (not with --true-masks, --shipped "
                 f"or --shutter), got {args.well_posed_grey}")
    if args.exposure_fraction is not None and not (args.exposure and 0 <= args.exposure_fraction <= 1):
        ap.error(f"--exposure-fraction needs --exposure and a fraction in [0, 1], got {args.exposure_fraction}")
    if args.exposure_taps is not None and not (args.exposure and (args.exposure_taps == 0 or args.exposure_taps >= 2)):
        ap.error(f"--exposure-taps needs --exposure and 0 (a camera) or at least 2 sub-frames, got {args.exposure_taps}")
    if args.chroma_weight is not None and (args.true_masks or args.shipped or not args.chroma_weight > 0):
        ap.error(f"--chroma-weight needs a positive weight and segmented concealed recordings, got {args.chroma_weight}")
    if args.shutter and (args.fresh or args.shipped or args.chroma_weight is not None):
        ap.error("--shutter is its own set: not with --fresh, --shipped or --chroma-weight")
    if args.sharp and (args.shutter or args.shipped):
        ap.error("--sharp is a concealed set without motion blur: not with --shutter or --shipped")
    if args.crf is not None and (args.shutter or args.shipped or args.sharp):
        ap.error("--crf is a concealed set at another H.264 quality: not with --shutter, --shipped or --sharp")
    if args.scale < 1 or (args.scale != 1 and (args.shutter or args.shipped)):
        ap.error(f"--scale is a concealed set through a camera of N >= 1 times the pixels (not with --shutter or "
                 f"--shipped), got {args.scale}")
    if args.fps_scale != 1 and (args.shutter or args.shipped):
        ap.error(f"--fps-scale is a concealed set filmed at another frame rate (not with --shutter or "
                 f"--shipped), got {args.fps_scale}")
    if args.extra and (args.shutter or args.shipped):
        ap.error("--with adds a candidate to a concealed set: not with --shutter or --shipped")
    if (args.transfer and (args.shutter or args.shipped or args.true_masks)) or (args.read_as and not args.transfer):
        ap.error("--transfer is a segmented concealed set stored through a camera curve (not with --shutter, "
                 "--shipped or --true-masks); --read-as only with --transfer")
    if args.shuffle_error is not None and not (args.sharp and args.exposure and not args.true_masks):
        ap.error(f"--shuffle-error {args.shuffle_error} needs --sharp (exact masks at the frames' instants) and "
                 "--exposure (the soft coverage it moves the error of), and not --true-masks")
    main(args.names, true_masks=args.true_masks, shipped=args.shipped, fresh=args.fresh, table_only=args.table,
         against=args.compare, chroma_weight=args.chroma_weight, shutter=args.shutter, extra=tuple(args.extra),
         edge_px=args.edge_px, sharp=args.sharp, crf=args.crf, albedo_passes=args.albedo_passes,
         transfer=args.transfer, read_as=args.read_as, exposure=args.exposure,
         exposure_fraction=args.exposure_fraction, coverage_near_px=args.coverage_near_px,
         coverage_clip=False if args.unclipped else None, fit_exposure=args.fit_exposure,
         point_spread=point_spread, baseline_starts=args.baseline_starts, exposure_taps=args.exposure_taps,
         coverage_band="motion" if args.motion_band else None, shading_fit="linear" if args.linear_shading else None,
         well_posed_grey=args.well_posed_grey, interior_shading=True if args.interior_shading else None,
         speed_noise=args.speed_noise, heldout_margin=args.heldout_margin, robust=args.robust,
         declare_lens=args.declare_lens, backcast=args.backcast, search_final=args.search_final, scale=args.scale,
         fps_scale=args.fps_scale, jump_sigmas=jump_sigmas, jump_one_at_a_time=args.jump_one_at_a_time,
         jump_neighbours=args.jump_neighbours, jump_refined=args.jump_refined, shuffle_error=args.shuffle_error)
