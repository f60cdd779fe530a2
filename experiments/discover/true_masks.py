"""Discover's baseline and single-effect refits on a recording's true masks instead of its segmented ones.

    python experiments/discover/true_masks.py FOLDER_OR_NAME [effects] [--segmented]   # ~3-8 min

FOLDER_OR_NAME: a shipped recording's name (``cylinder``) or a recording folder with video.mp4,
camera.json, mesh.obj, truth.json and masks.npz (``experiments/discover/recordings/control_cylinder``).
effects: comma-separated (default ``time_scale,quadratic_drag``). With ``--segmented`` the video's
segmented masks are used, as discover does; otherwise MuJoCo's true masks. (``--render=CROP,SIGMA``,
the refits' render crop and edge width, went when the refits took exact moments, 2026-11-26.) Where
a refit on the true masks finds nothing and the same refit on the segmented masks does, the segmentation, not the
model or the renderer, made the difference. Prints each model's parameters, edge bias, ΔBIC and
held-out centroid error.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from torchfit.camera import Camera
from torchfit.discover import _criterion
from torchfit.discover_video import VideoProblem
from torchfit.losses import central_moments, raw_from_central
from torchfit.paper._recording import load_recording
from torchfit.run import build_problem
from torchfit.shape import load_shape
from torchfit.video import SegmentationSettings, _boxes, load_observation, raw_moments

HERE = Path(__file__).resolve().parent


def fps_factor(text: str) -> Fraction:
    """``--fps-scale``'s value: a positive fraction ``P/Q`` or whole ``N`` (``5/6``: 50 fps from the
    sets' 60); anything else is refused with the value named."""
    try:
        factor = Fraction(text)
    except (ValueError, ZeroDivisionError):
        factor = None
    if factor is None or factor <= 0:
        raise ValueError(f"a frame-rate factor is a positive N, 1/N or P/Q, got {text!r}")
    return factor


def fps_suffix(fps_scale: Fraction | int) -> str:
    """The folder suffix of a set filmed at ``fps_scale`` times the frame rate: ``_fps2`` for twice,
    ``_fps1by2`` for half, ``_fps5by6`` for 5/6, nothing for the set's own."""
    fps_scale = Fraction(fps_scale)
    if fps_scale == 1:
        return ""
    return f"_fps{fps_scale.numerator}" + (f"by{fps_scale.denominator}" if fps_scale.denominator != 1 else "")


def fresh_folder(fresh: int, sharp: bool = False, crf: int | None = None, transfer: str | None = None,
                 scale: int = 1, fps_scale: Fraction | int = 1, plain: bool = False) -> Path:
    """Where concealed set ``fresh`` lives (0: the first set; ``sharp``: its copy without motion blur;
    ``crf``: its copy encoded at that H.264 quality; ``transfer``: its copy stored through that
    curve; ``scale``: its copy filmed with ``scale`` times the pixels along each side, ``_x<scale>``;
    ``fps_scale``: its copy filmed at ``fps_scale`` times the frame rate, ``fps_suffix``;
    ``plain``: its copy in front of a plain wall and floor, ``_plain``).
    Here, not in make_concealed.py, so that concealed.py finds the sets without MuJoCo."""
    folder = HERE / (f"recordings_fresh{fresh}" if fresh else "recordings")
    return folder.with_name(folder.name + ("_sharp" if sharp else "") + (f"_crf{crf}" if crf is not None else "")
                            + (f"_{transfer}" if transfer else "") + (f"_x{scale}" if scale != 1 else "")
                            + fps_suffix(fps_scale) + ("_plain" if plain else ""))


def recording_parts(folder: Path) -> tuple[dict, object, Camera]:
    """A concealed recording folder's ``truth.json`` (dict), object (:class:`torchfit.shape.Shape`,
    from ``mesh.obj`` at the true density) and camera (``camera.json``)."""
    truth = json.loads((folder / "truth.json").read_text())
    return truth, load_shape(folder / "mesh.obj", density=truth["object"]["density"]), Camera.from_file(folder / "camera.json")


def subframe_times(truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """A generated recording's (T,) frame times and (T, K) blur sub-frame times as it was rendered
    (make_recordings.sample_times): K evenly over ``exposure_frac / fps``, centred on the frame;
    one sub-frame (a sharp recording) at the frame's own time."""
    subframes, exposure = int(truth["render"]["blur_subframes"]), float(truth["render"]["exposure_frac"])
    times = np.array(truth["per_frame"]["time"])
    offsets = np.arange(subframes) / (subframes - 1) - 0.5 if subframes > 1 else np.zeros(1)
    return times, times[:, None] + offsets * exposure / float(truth["fps"])


def load_problem(folder: Path, shape, camera: Camera, true_masks: bool, settings: SegmentationSettings | None = None):
    """A recording's observation, fit problem (float32, CPU) and span: its video segmented as
    discover does (with ``settings``, default the defaults), or with the engine's true masks
    (``masks.npz``) in place of the segmentation."""
    observation = load_observation(str(folder / "video.mp4"), camera=camera, settings=settings)
    if true_masks:
        observation = with_masks(observation, np.load(folder / "masks.npz")["masks"].astype(bool))
    return (observation, *problem_of(observation, shape, camera))


def with_masks(observation, masks: np.ndarray):
    """``observation`` with (T, H, W) bool ``masks`` (and their boxes) in place of its own."""
    return dataclasses.replace(observation, masks=masks, boxes=_boxes(masks), coverage_moments=raw_moments(masks))


def both_frames(segmented: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """Indices of the frames where both (T, 6) raw moments are non-empty."""
    return np.flatnonzero((segmented[:, 0] > 0) & (exact[:, 0] > 0))


def error_moved(segmented: np.ndarray, exact: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(T, 6) raw moments: the ``exact`` (T, 6) moments, each frame carrying the ``segmented``
    (T, 6) moments' error of the frame ``order`` names.

    ``order``: (F,) a permutation of 0..F-1 over the F frames where both are non-empty
    (:func:`both_frames`, in frame order): the k-th of them takes the error of the
    ``order[k]``-th. Frames where either is empty keep the segmented moments. A frame's error is
    its area ratio, its centroid offset (pixels) and its covariance's offset relative to the exact
    one's trace (the object's size squared, which differs a little from frame to frame); the
    identity ``order`` gives ``segmented`` back. Moments to and from area, centroid and covariance
    by :func:`torchfit.losses.central_moments` and :func:`torchfit.losses.raw_from_central`.
    """
    both = both_frames(segmented, exact)
    if sorted(np.asarray(order).tolist()) != list(range(len(both))):
        raise ValueError(f"order must permute the {len(both)} frames where both are non-empty, got {order}")
    a_s, c_s, s_s = central_moments(torch.as_tensor(segmented[both], dtype=torch.float64))
    a_e, c_e, s_e = central_moments(torch.as_tensor(exact[both], dtype=torch.float64))
    size = s_e.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    order = torch.as_tensor(order)
    moved = raw_from_central(a_e * (a_s / a_e)[order], c_e + (c_s - c_e)[order], s_e + ((s_s - s_e) / size)[order] * size)
    out = np.asarray(segmented, np.float64).copy()
    out[both] = moved.numpy()
    return out


def with_error_shuffled(observation, masks: np.ndarray, seed: int | tuple[int, ...]):
    """``observation`` whose soft coverage's moments are the (T, H, W) bool exact ``masks``' moments
    carrying its own per-frame error (against them) in a shuffled order (:func:`error_moved`, a
    permutation drawn from ``seed``, numpy's seed sequence): the error's size, spread, tails and
    mean stay, its order in time and its tie to the throw go."""
    exact, seg = raw_moments(masks), observation.coverage_moments
    order = np.random.default_rng(seed).permutation(len(both_frames(seg, exact)))
    return dataclasses.replace(observation, coverage_moments=error_moved(seg, exact, order))


def problem_of(observation, shape, camera: Camera):
    """The fit problem (float32, CPU) of an observation, and its span of frames."""
    return build_problem(observation, shape, camera, g=9.81, dtype=torch.float32, device=torch.device("cpu"))


def main(target: str, effects: tuple[str, ...], segmented: bool) -> None:
    if "/" in target:
        folder = Path(target)
        _, shape, camera = recording_parts(folder)
    else:
        rec = load_recording(target)
        folder, shape, camera = rec.folder, rec.shape, rec.camera
    _, problem, _ = load_problem(folder, shape, camera, true_masks=not segmented)
    video = VideoProblem(problem, candidates=effects, progress=print)
    base = video.fit((), None)
    print(f"masks: {'segmented' if segmented else 'true'}; baseline edge bias {base.payload['edge_px']['value']:+.3f} px, "
          f"held-out centroid {base.payload['heldout_centroid_px']:.3f} px")
    for effect in effects:
        refit = video.fit((effect,), base)
        delta_bic = _criterion(base, video.noise_var)[1] - _criterion(refit, video.noise_var)[1]
        params = {p: f"{v['value']:.4g} ± {v['std']:.2g}" for p, v in refit.params[effect].items()}
        print(f"+ {effect}: {params}, edge {refit.payload['edge_px']['value']:+.3f} px, ΔBIC {delta_bic:.1f}, "
              f"held-out centroid {base.payload['heldout_centroid_px']:.3f} -> {refit.payload['heldout_centroid_px']:.3f} px")


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if not args:
        sys.exit(__doc__)
    main(args[0], tuple((args[1] if len(args) > 1 else "time_scale,quadratic_drag").split(",")), "--segmented" in sys.argv)
