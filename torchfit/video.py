"""Video front end: a recording in, per-frame object masks, boxes and frame flags out.

Inputs are a video file (anything OpenCV reads), a folder of images (sorted by name) or a
folder of masks (PNG, object = non-zero). Video and images are segmented against a model of
the static scene:

1. background ``B``: the temporal median of the frames (default; the object moves, so the
   median sees the scene) or the background image of OpenCV's MOG2 model;
2. detection: colour difference ``|I - B|`` above ``noise_sigmas`` robust standard deviations
   of the difference image (MAD based), opened with a small structuring element; the object
   seed is the largest connected component;
3. boundary: motion blur and partial pixel coverage make the object's edge a mixture
   ``I = a F + (1 - a) B``. The object's colour is ``F = s A``: an albedo direction ``A``
   (estimated from confident object pixels) times a shading ``s`` that differs between faces.
   a. Per pixel, ``(a, u = a s)`` is a 2-unknown least-squares fit, independent of shading.
      It rests on the colour angle between ``A`` and ``B`` (often ~15 degrees), that is on
      chroma, which video stores at half resolution.
   b. The shading is smooth on the object, so ``s`` is fitted locally instead: a Gaussian-
      weighted least squares of ``u = a s`` over the neighbourhood. With ``F = s A`` known, the
      coverage is the 1-unknown projection ``a = (I - B).(F - B) / |F - B|^2``. It uses the
      brightness difference (full-resolution luma) as well as colour. Where the background is
      too dark or too close to ``A`` in colour for step a, the shading comes from neighbours.
   The mask is ``a >= 0.5``: for an exposure centred on the frame time a moving edge is half
   covered exactly at its position at that time. Closed, largest component, holes filled.
   The coverage itself, within ``SegmentationSettings.coverage_near_px`` of the mask (clipped to
   [0, 1] unless ``SegmentationSettings.coverage_clip`` is off), is kept as its raw moments
   (``Observation.coverage_moments``): moments are linear in coverage, so a blurred frame's are
   the exposure's average of the silhouette's (what ``discover`` compares with an exposure,
   :class:`torchfit.search.Exposure`).

The mixing model holds in light. A camera stores light through a curve (BT.709, sRGB), so the
values are decoded to light before any of the above, through the curve the file names
(``SegmentationSettings.transfer = "auto"``, :func:`stored_transfer`) or the one set; torchfit's
generated recordings name none, mix in their stored values and are read as they are (``linear``).

A camera held in the hand moves a little between frames, and the model projects the flight
through one still camera. Before anything above, each frame's move against the clip's background
is measured (:func:`camera_motion`: a turn of the camera about its three axes, seen through its
intrinsics, and a shift of the picture); where some pixel of the background moves by more than
:data:`STILL_PX`, the frames are moved back (``SegmentationSettings.stabilise``) and the
observation keeps the motion.

Frames that should not be fitted keep their place in every per-frame array and are flagged
``used=False`` with a reason. Segmentation results are cached in ``cache_dir``.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from scipy import ndimage

from torchfit.camera import Camera

__all__ = [
    "Observation",
    "SegmentationSettings",
    "load_observation",
    "raw_moments",
    "read_frames",
    "observed_frames",
    "camera_motion",
    "camera_motion_note",
    "camera_motion_fields",
    "stabilised",
    "unseen_pixels",
    "stored_transfer",
    "contact_sheet",
    "BACKGROUND_METHODS",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
KINDS = ("auto", "video", "images", "masks")
BACKGROUND_METHODS = ("median", "mog2")
TRANSFERS = ("auto", "linear", "srgb", "bt709", "hlg")
COVERAGE_BANDS = ("steps", "motion")
SHADING_FITS = ("constant", "linear")
_CACHE_VERSION = 10
# stabilise="auto": the frames are moved back when some pixel of some frame's background lies more
# than this many pixels from the clip's (camera_motion; a frame's corners, where a turn moves most).
# The 160 still concealed recordings move no pixel more than 0.052 px; refilmed with a smooth shake
# of 1 px RMS per axis, three of five controls named an effect unless the frames were moved back,
# and none when they were (experiments/discover/HISTORY.md, *A camera that is not quite still*,
# *Taking out a turn about the line of sight*, *A registration by the homography*).
STILL_PX = 0.25
# camera_motion: pixels whose grey level lies this far from the aligned background are the object's
# (or another mover's) and are left out of the registration, grown by MOTION_OBJECT_GROW_PX
MOTION_OBJECT_DIFF = 20.0
MOTION_OBJECT_GROW_PX = 9
# stabilised: Lanczos-4 draws on pixels this far away, so a moved-back frame's edge this deep is unseen
LANCZOS_REACH_PX = 4
MOTION_PYRAMID_MIN_PX = 48  # camera_motion's coarsest level keeps at least this many pixels a side
MOTION_ITERATIONS = 50  # camera_motion's Gauss-Newton steps at most, per pyramid level
MOTION_STEP_PX = 1e-3  # ... and a level stops when a step moves no corner more (that level's px)
MOTION_SCORE_DROP = 0.05  # a level whose steps lower the correlation more than this keeps its start
# a frame whose background correlates less than this with the clip's, once registered, keeps its map
# (_register): a background with too little texture (a flat wall, the sky) registers its noise and
# the object
MOTION_MIN_CORRELATION = 0.8
# camera_motion's standard errors: the Gauss-Newton's, its residuals taken as correlated within tiles of
# MOTION_TILE_PX a side, times this: the RMS corner error over the RMS standard error of the 40 still
# recordings of fresh concealed sets 1 and 2 (1.075; 0.83-1.16 a recording once scaled). On shaken
# and on plainer backgrounds the errors run 1.4-1.8 times the standard errors (experiments/discover/
# HISTORY.md, *A background with little texture*, *Passes until the maps settle*)
MOTION_SIGMA_FACTOR = 1.075
MOTION_TILE_PX = 16
# camera_motion passes with the object masked until one moves no frame's corner more than this against
# the pass before, at most MOTION_MAX_PASSES in all: against a plain wall the first pass, the object in,
# is dragged by its move, and the second cannot pull the map back along the wall's flat direction
# (experiments/discover/HISTORY.md, *Passes until the maps settle*)
MOTION_SETTLED_PX = 0.1
MOTION_MAX_PASSES = 4
MOTION_MARGIN_PX = 2  # a level registers the pixels its start maps at least this far inside the frame
MOTION_POINTS = 40_000  # ... of at most this many valid pixels, the steepest in the reference
# coverage_near_px="auto": the band of BAND_REFERENCE_STEPS steps chosen on a camera of this many pixels
BAND_REFERENCE_STEPS, BAND_REFERENCE_PIXELS = 4, 640 * 480


@dataclass(frozen=True)
class SegmentationSettings:
    """Settings of the segmentation (all part of the cache key).

    Attributes:
        method: background model, one of ``BACKGROUND_METHODS``.
        noise_sigmas: detection threshold in robust standard deviations of ``|I - B|``.
        alpha_threshold: coverage at which a pixel counts as object (0.5: the edge position
            at the frame time for a centred exposure).
        alpha_smoothing: Gaussian sigma (pixels) applied to the coverage before thresholding.
        shading_radius: Gaussian sigma (pixels) of the neighbourhood the local shading is
            fitted over (0: no local shading, the per-pixel 2-unknown fit only).
        shading_fit: ``"constant"``: the shading is taken as constant over that neighbourhood;
            ``"linear"``: as a plane (a local-linear fit), so that at a limb which darkens toward
            its edge (a lit ball) the fit does not borrow the brighter inside. On a synthetic
            shaded ball the constant reads the coverage 4 % large with an excess variance of
            0.6 px² (experiments/discover/shading_limb.py; HISTORY.md, *Nineteenth session*).
        chroma_weight: weight of the two colour-difference channels against luma when the
            coverage is solved. Video codecs store colour at half resolution (4:2:0), so its
            edges are blurred; 0.5 trusts full-resolution luma more without dropping colour.
        transfer: how the recording's pixel values encode light, one of ``TRANSFERS``. The
            mixing model ``I = a F + (1 - a) B`` of an edge pixel (partial coverage, motion blur)
            holds in light, which a camera sums before it encodes the sum: ``"srgb"`` (the
            piecewise sRGB curve), ``"bt709"`` (the BT.709 camera curve of most phone and
            camera video) and ``"hlg"`` (hybrid log-gamma, phones' HDR video) decode each value
            to linear light first (scaled to 0..255); ``"linear"`` takes the values as they are,
            right for footage that is linear or was mixed in its stored values, as torchfit's
            and the experiments' generated recordings are. ``"auto"`` (the default) takes the
            curve the file names (:func:`stored_transfer`: an MP4/MOV file's colour tag, a PNG's
            colour chunks; JPEG is sRGB) and ``"linear"`` where it names none. On encoded
            footage ``"linear"`` misreads a blurred edge's coverage (a dark disc on a light
            background read -0.14 too little on its ramp, ``tests/test_video.py``), so its
            outline moves with its speed.
        albedo_passes: passes that re-estimate the object's albedo direction from the pixels the
            previous pass calls covered (coverage >= ``PURE_COVERAGE``), instead of from every
            eroded detection pixel. On a blurred or thin object most of those are partly covered
            and the albedo tilts toward the background, so edges read too much coverage (a
            synthetic blurred disc: +0.08 on its ramp with 0 passes, 0.0001 with 1). It lowers the
            segmentation's error on the concealed recordings but made discover's verdicts worse
            there (experiments/discover/HISTORY.md, *The albedo from covered pixels*), so it is
            off by default.
        coverage_near_px: the soft coverage's moments (``Observation.coverage_moments``) count
            the pixels within this many 4-neighbour steps of the final mask. A blurred edge's ramp
            reaches past 4 at these recordings' speeds, so 4 reads short of the true blur; a wider
            band keeps more background noise, which the clip to [0, 1] turns into mass. A band
            of 6 reads the blur nearly right but let discover name a wrong clock on a concealed
            ball, so 4 steps stay at 640 x 480 (experiments/discover/HISTORY.md, *Reading the
            exposure from the blur*). ``"auto"`` (the default): those 4 steps in a 640 x 480
            camera's units, ``round(4 s)`` with ``s = sqrt(H W / (640 480))``
            (:meth:`band_steps`): a thrown object's blurred ramp is as many more pixels wide as
            the camera has more pixels across the same view. Through 1280 x 960 a band of 4 cut
            it; 8 named 72 of 90 hidden effects on six concealed sets against 67 at 640 x 480,
            29 of 30 controls quiet (experiments/discover/HISTORY.md, *Forty-first session*,
            *Forty-second session*). An int is a fixed band.
        coverage_band: ``"steps"``: the moments count the band of ``coverage_near_px`` steps;
            ``"motion"``: that band swept half the frame's travel either way along the motion
            (:func:`motion_band`; the travel is the mask centroid's, central differences over
            the frames), so a fast blur's ramp is kept whole along the motion while the band
            across it stays as narrow as with ``"steps"`` (experiments/discover/HISTORY.md,
            *Nineteenth session*).
        coverage_clip: clip the coverage to [0, 1] before its moments are taken. The clip turns
            the zero-mean noise of every background pixel in the band into mass, so the moments
            grow with the band; unclipped they stop growing once the band holds the blurred
            ramp. Unclipped within a band of 8, discover still named the same wrong clock on a
            concealed ball as a clipped band of 6, so the clip stays on
            (experiments/discover/HISTORY.md, *The clip that made mass*).
        well_posed_grey: the per-pixel 2-unknown fit (coverage and shading) is trusted where the
            background's colour off the albedo's direction, ``|B| sin(angle(A, B))``, exceeds
            this many grey levels (luma/chroma); elsewhere the coverage falls back to
            ``|D| / contrast`` and the local shading takes no support from the pixel. At 10 a
            shaded face over the concealed recordings' dark grass (``|B| sin`` ~7-9) took its
            shading from the lit face beside it and was lost (read a fifth to a half covered).
            At 5 the coverage's far-off frames on those recordings are fewer, but discover named
            29 of 45 hidden effects on three concealed sets against 31 at 10, so 10 stays the
            default (experiments/discover/HISTORY.md, *Sixtieth session*).
        interior_shading: where the per-pixel fit is not trusted (the background too dark or
            too like the object, ``well_posed_grey``), the local shading also takes support from
            the object's own interior: pixels of the detection (the seed) further inside it than
            the coverage band's steps (:meth:`band_steps`) and half a frame's travel along the
            motion (:func:`motion_band`, the seed's travel), so beyond any blur's reach, taken as
            fully covered: their shading is ``I . A``. Without it the shading of an edge over a dark background is
            borrowed from trusted pixels up to a wide window away (often another face), or the
            coverage falls back to ``|D| / contrast``. Off here; the command line's
            ``data.segmentation.interior_shading: null`` turns it on where discover models the
            motion blur, the path it was measured on (experiments/discover/HISTORY.md,
            *Sixty-second session*: the setting, its gate, runs and verdict).
        morph_radius: radius (pixels) of the square opening / closing elements.
        min_area: smallest object area in pixels; smaller components are noise.
        second_component_frac: a frame whose second largest detection component is at least
            this fraction of the largest is flagged ``several large components``.
        area_jump: a frame whose area differs by more than this factor from the median area
            of its clean neighbours (three each side) is flagged.
        max_background_frames: frames (evenly spaced) that feed the background model.
        stabilise: move each frame back by its background's move (:func:`camera_motion`, the
            camera's turn and a shift) before anything else, so a camera that shook in the hand
            is seen as a still one: ``True``, ``False`` (the motion is still measured and reported) or
            ``"auto"`` (the default): when some pixel of some frame moved more than
            :data:`STILL_PX`.
    """

    method: str = "median"
    noise_sigmas: float = 6.0
    alpha_threshold: float = 0.5
    alpha_smoothing: float = 1.0
    shading_radius: float = 1.5
    shading_fit: str = "constant"
    chroma_weight: float = 0.5
    transfer: str = "auto"
    albedo_passes: int = 0
    coverage_near_px: int | str = "auto"
    coverage_band: str = "steps"
    coverage_clip: bool = True
    well_posed_grey: float = 10.0
    interior_shading: bool = False
    morph_radius: int = 1
    min_area: int = 6
    second_component_frac: float = 0.5
    area_jump: float = 2.0
    max_background_frames: int = 60
    stabilise: bool | str = "auto"

    def __post_init__(self) -> None:
        if not (self.stabilise is True or self.stabilise is False or self.stabilise == "auto"):
            raise ValueError(f'stabilise must be true, false or "auto", got {self.stabilise!r}')
        if self.method not in BACKGROUND_METHODS:
            raise ValueError(
                f'Invalid method "{self.method}". Must be one of {", ".join(BACKGROUND_METHODS)}'
            )
        if self.transfer not in TRANSFERS:
            raise ValueError(f"transfer must be one of {TRANSFERS}, got {self.transfer!r}")
        for name in ("noise_sigmas", "alpha_smoothing", "shading_radius", "chroma_weight", "well_posed_grey"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 < self.alpha_threshold < 1.0:
            raise ValueError(f"alpha_threshold must be in (0, 1), got {self.alpha_threshold!r}")
        if self.area_jump <= 1.0:
            raise ValueError(f"area_jump must be > 1, got {self.area_jump!r}")
        if self.albedo_passes < 0:
            raise ValueError(f"albedo_passes must be >= 0, got {self.albedo_passes!r}")
        if self.shading_fit not in SHADING_FITS:
            raise ValueError(f"shading_fit must be one of {SHADING_FITS}, got {self.shading_fit!r}")
        if self.coverage_band not in COVERAGE_BANDS:
            raise ValueError(f"coverage_band must be one of {COVERAGE_BANDS}, got {self.coverage_band!r}")
        if not (self.coverage_near_px == "auto" or (isinstance(self.coverage_near_px, int)
                                                     and not isinstance(self.coverage_near_px, bool)
                                                     and self.coverage_near_px >= 1)):
            raise ValueError(f'coverage_near_px must be a whole number of steps >= 1 or "auto", '
                             f"got {self.coverage_near_px!r}")
        if self.min_area < 1 or self.morph_radius < 0 or self.max_background_frames < 1:
            raise ValueError(
                "min_area and max_background_frames must be >= 1 and morph_radius >= 0, got "
                f"{self.min_area!r}, {self.max_background_frames!r}, {self.morph_radius!r}"
            )

    def band_steps(self, height: int, width: int) -> int:
        """The coverage band in 4-neighbour steps for frames of ``height`` x ``width`` pixels:
        ``coverage_near_px`` itself, or for ``"auto"`` ``round(4 sqrt(H W / (640 480)))``, at
        least 1 (4 at 640 x 480, 8 at 1280 x 960, 10 at 1920 x 1080)."""
        if self.coverage_near_px != "auto":
            return int(self.coverage_near_px)
        return max(1, round(BAND_REFERENCE_STEPS * math.sqrt(height * width / BAND_REFERENCE_PIXELS)))


@dataclass
class Observation:
    """What the fit consumes from one recording.

    Attributes:
        masks: (T, H, W) bool object masks (undistorted when the camera has distortion).
        boxes: (T, 4) float ``(x0, y0, x1, y1)``, pixel-centre coordinates, inclusive
            (``x1`` is the last column index); NaN where a frame has no object.
        used: (T,) bool, False for frames to leave out of the fit.
        reasons: T strings, ``""`` for used frames, else why the frame is left out.
        fps: frames per second.
        frame_indices: (T,) int64 index of each frame in the source.
        camera: intrinsics, if given.
        source: the input path.
        kind: ``"video"``, ``"images"`` or ``"masks"``.
        from_cache: True when the masks were loaded from the cache, not segmented.
        background: (H, W, 3) uint8 RGB background model (distorted, as recorded), or None
            for mask input.
        areas: (T,) int64 mask areas, pixels.
        transfer: the curve the pixel values were decoded through (``SegmentationSettings.transfer``,
            ``"auto"`` resolved by :func:`stored_transfer`); ``""`` for mask input.
        transfer_note: where that curve came from, a sentence.
        coverage_moments: (T, 6) raw moments ``(m00, m10, m01, m20, m11, m02)`` about the image
            origin (pixel centres at integers) of each frame's soft coverage (the mask's own for
            mask input; zeros where a frame has no object), undistorted with the masks (the
            coverage resampled through the camera's undistortion before its moments are taken);
            None for an observation made without them.
        camera_motion: (T, 3, 3) each frame's background move against the clip's, a homography
            from a still camera's pixel to the frame's (:func:`camera_motion`); None for mask input.
        stabilised: True when the frames were moved back by ``camera_motion`` before they were
            segmented (``SegmentationSettings.stabilise``): the masks are then in the still
            camera's place, and :func:`observed_frames` gives the frames as segmented.
        camera_correlation: (T,) how well each frame's background, moved back, correlates with
            the clip's (:class:`CameraMotion`); None for mask input. A frame under
            :data:`MOTION_MIN_CORRELATION` did not register (:attr:`camera_registered`).
        camera_sigma_px: (T,) the standard error of each frame's map at its least certain corner
            (px; NaN where nothing was compared; :class:`CameraMotion`); None for mask input.
    """

    masks: np.ndarray
    boxes: np.ndarray
    used: np.ndarray
    reasons: list[str]
    fps: float
    frame_indices: np.ndarray
    camera: Camera | None
    source: str
    kind: str
    from_cache: bool = False
    background: np.ndarray | None = None
    areas: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    transfer: str = ""
    transfer_note: str = ""
    coverage_moments: np.ndarray | None = None
    camera_motion: np.ndarray | None = None
    stabilised: bool = False
    camera_correlation: np.ndarray | None = None
    camera_sigma_px: np.ndarray | None = None

    @property
    def camera_registered(self) -> np.ndarray | None:
        """(T,) bool, the frames whose background registered (:class:`CameraMotion`); None for
        mask input."""
        return None if self.camera_correlation is None else self.camera_correlation >= MOTION_MIN_CORRELATION

    @property
    def camera_moved_px(self) -> float:
        """The largest move of any pixel of any frame's background (px; 0 without a measurement)."""
        return 0.0 if self.camera_motion is None else _largest_move(self.camera_motion, self.masks.shape[1:3])

    @property
    def times(self) -> np.ndarray:
        """(T,) seconds, 0 at the first frame (``t = i / fps``)."""
        return np.arange(len(self.frame_indices)) / self.fps


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _check_range(start: int, stop: int | None, count: int, source: str) -> int:
    if count == 0:
        raise ValueError(f"{source!r} has no frames")
    stop = count if stop is None else stop
    if not (0 <= start < count):
        raise ValueError(f"start = {start} is out of range for {source!r} with {count} frames")
    if not (start < stop <= count):
        raise ValueError(
            f"stop = {stop} is out of range for {source!r} with {count} frames "
            f"(expected {start} < stop <= {count})"
        )
    return stop


def _read_video(path: Path, start: int, stop: int | None) -> tuple[np.ndarray, float]:
    """(T, H, W, 3) uint8 BGR frames ``start:stop`` and the file's fps (0 if unknown)."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ValueError(
            f"could not read video {str(path)!r}: OpenCV cannot open it (not a video it "
            "decodes, or a video with no frames)"
        )
    try:
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        frames = []
        index = 0
        while stop is None or index < stop:
            ok, frame = capture.read()
            if not ok:
                break
            if index >= start:
                frames.append(frame)
            index += 1
    finally:
        capture.release()
    _check_range(start, stop, index, str(path))
    return np.stack(frames), fps


def _read_image(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise ValueError(f"could not read image {str(path)!r}")
    return image


def _read_image_folder(paths: list[Path], start: int, stop: int | None) -> np.ndarray:
    stop = _check_range(start, stop, len(paths), str(paths[0].parent) if paths else "")
    frames = []
    for path in paths[start:stop]:
        image = _read_image(path, cv2.IMREAD_COLOR)
        if frames and image.shape != frames[0].shape:
            raise ValueError(
                f"image {str(path)!r} has size {image.shape[1]}x{image.shape[0]}, "
                f"expected {frames[0].shape[1]}x{frames[0].shape[0]} like the first"
            )
        frames.append(image)
    return np.stack(frames)


def _read_mask_folder(paths: list[Path], start: int, stop: int | None) -> np.ndarray:
    stop = _check_range(start, stop, len(paths), str(paths[0].parent) if paths else "")
    masks = []
    for path in paths[start:stop]:
        image = _read_image(path, cv2.IMREAD_UNCHANGED)
        mask = image != 0 if image.ndim == 2 else (image != 0).any(axis=-1)
        if masks and mask.shape != masks[0].shape:
            raise ValueError(
                f"mask {str(path)!r} has size {mask.shape[1]}x{mask.shape[0]}, "
                f"expected {masks[0].shape[1]}x{masks[0].shape[0]} like the first"
            )
        masks.append(mask)
    return np.stack(masks)


def _looks_like_masks(paths: list[Path]) -> bool:
    """True when the first images are single-channel (or grey) with at most two values."""
    for path in paths[:3]:
        image = _read_image(path, cv2.IMREAD_UNCHANGED)
        if image.ndim == 3:
            if not all(np.array_equal(image[..., 0], image[..., c]) for c in range(1, image.shape[2])):
                return False
            image = image[..., 0]
        if len(np.unique(image)) > 2 or (len(np.unique(image)) == 2 and image.min() != 0):
            return False
    return True


def read_frames(source: str | Path, frame_indices) -> np.ndarray:
    """Read frames of a video or image folder by index.

    Args:
        source: video file or image folder.
        frame_indices: (N,) indices into the source.

    Returns:
        (N, H, W, 3) uint8 RGB frames.
    """
    path = Path(source)
    indices = [int(i) for i in np.asarray(frame_indices).ravel()]
    if not indices:
        raise ValueError("frame_indices must not be empty")
    if path.is_dir():
        paths = _list_images(path)
        if max(indices) >= len(paths) or min(indices) < 0:
            raise ValueError(f"frame index out of range for {str(path)!r} with {len(paths)} images")
        frames = [_read_image(paths[i], cv2.IMREAD_COLOR) for i in indices]
    else:
        video, _ = _read_video(path, min(indices), max(indices) + 1)
        frames = [video[i - min(indices)] for i in indices]
    return np.stack([cv2.cvtColor(f, cv2.COLOR_BGR2RGB) for f in frames])


def observed_frames(observation: Observation, positions=None) -> np.ndarray:
    """(N, H, W, 3) uint8 RGB frames of ``observation`` at ``positions`` (indices into its frames;
    all when None) as they were segmented: read from its source and, when it was stabilised,
    moved back by its :attr:`Observation.camera_motion` (:func:`stabilised`)."""
    positions = np.arange(len(observation.frame_indices)) if positions is None else np.asarray(positions)
    frames = read_frames(observation.source, observation.frame_indices[positions])
    if observation.stabilised:
        frames = stabilised(frames, observation.camera_motion[positions])
    return frames


def _motion_matrices(motion: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T, 3, 3) the rigid maps ``p -> R(p - c) + c + d`` of (T, 3) rows ``(dx, dy, turn)`` (px,
    px, degrees counter-clockwise on the screen, as ``cv2.getRotationMatrix2D``) about the centre
    ``c`` of an image of ``size`` ``(H, W)``: a shift and a turn of the picture as a map
    (:func:`camera_motion`'s kind without a camera; ``shake.py`` and the tests build with it)."""
    height, width = size
    centre = ((width - 1) / 2, (height - 1) / 2)
    out = np.tile(np.eye(3), (len(motion), 1, 1))
    for t, (dx, dy, turn) in enumerate(np.asarray(motion, float)):
        out[t, :2] = cv2.getRotationMatrix2D(centre, float(turn), 1.0)
        out[t, :2, 2] += (dx, dy)
    return out


def _mapped(maps: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(T, K, 2) where each of the (T, 3, 3) homographies ``maps`` sends the (K, 3) points
    ``(x, y, 1)``."""
    moved = np.einsum("tij,kj->tki", maps, points)
    return moved[..., :2] / moved[..., 2:]


def _motion_rows(maps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T, 3) rows ``(dx, dy, turn)`` of (T, 3, 3) maps (homographies) at the centre ``c`` of an
    image of ``size`` ``(H, W)``: where ``c`` moves, and the turn of the map's Jacobian there
    (degrees, counter-clockwise on the screen): :func:`_motion_matrices`' inverse for a rigid map."""
    height, width = size
    centre = np.array([(width - 1) / 2, (height - 1) / 2, 1.0])
    shift = _mapped(maps, centre[None])[:, 0] - centre[:2]
    w = maps[:, 2] @ centre  # (T,) the homogeneous scale at the centre
    jac = (maps[:, :2, :2] - np.einsum("ti,tj->tij", shift + centre[:2], maps[:, 2, :2])) / w[:, None, None]
    turns = np.degrees(np.arctan2(jac[:, 0, 1] - jac[:, 1, 0], jac[:, 0, 0] + jac[:, 1, 1]))
    return np.column_stack([shift, turns])


def _corners(size: tuple[int, int]) -> np.ndarray:
    """(4, 3) the corner pixels ``(x, y, 1)`` of an image of ``size`` ``(H, W)``, where a map of
    :func:`camera_motion`'s kind moves a pixel most (a homography's largest move lies on the image's
    boundary; for the small maps of a camera's shake, at a corner)."""
    height, width = size
    return np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], float)


def _frame_moves(maps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T,) the largest move (px) of any pixel of an image of ``size`` ``(H, W)`` under each of
    the (T, 3, 3) ``maps``, at a corner (:func:`_corners`)."""
    corners = _corners(size)
    return np.linalg.norm(_mapped(maps, corners) - corners[None, :, :2], axis=2).max(axis=1, initial=0.0)


def _largest_move(maps: np.ndarray, size: tuple[int, int]) -> float:
    """The largest of :func:`_frame_moves` (px; 0 for no frame)."""
    return float(_frame_moves(maps, size).max(initial=0.0))


def camera_motion_fields(observation: Observation) -> dict:
    """What ``result.json`` and ``discover.json`` record of the camera's motion: each frame's
    background move against the clip's, the image centre's shift ``camera_motion_px`` (T lists
    ``[x, y]``), the turn about it ``camera_turn_deg`` (T values, counter-clockwise on the
    screen; :func:`_motion_rows`) and the whole map ``camera_maps`` (T 3 x 3 homographies, a still
    camera's pixel to the frame's), each frame's background correlation with the clip's
    ``camera_correlation`` (null where none), whether it registered ``camera_registered`` and
    the standard error of its map at its least certain corner ``camera_sigma_px`` (px, null
    where none; :class:`CameraMotion`), all None for mask input, and ``stabilised``, whether the frames
    were moved back by it before the segmentation (:func:`camera_motion`)."""
    maps, correlation = observation.camera_motion, observation.camera_correlation
    rows = None if maps is None else _motion_rows(maps, observation.masks.shape[1:3])
    registered = observation.camera_registered
    return {"camera_motion_px": None if rows is None else rows[:, :2].tolist(),
            "camera_turn_deg": None if rows is None else rows[:, 2].tolist(),
            "camera_maps": None if maps is None else np.asarray(maps).tolist(),
            "camera_correlation": None if correlation is None else [
                float(c) if math.isfinite(c) else None for c in correlation],
            "camera_registered": None if registered is None else registered.tolist(),
            "camera_sigma_px": None if observation.camera_sigma_px is None else [
                float(c) if math.isfinite(c) else None for c in observation.camera_sigma_px],
            "stabilised": bool(observation.stabilised)}


def _frame_spans(frames: np.ndarray) -> str:
    """(N,) sorted frame numbers as runs: ``"3, 7-9, 12"``."""
    spans, start = [], None
    for i, f in enumerate(frames):
        start = f if start is None else start
        if i + 1 == len(frames) or frames[i + 1] != f + 1:
            spans.append(f"{start}" if start == f else f"{start}-{f}")
            start = None
    return ", ".join(spans)


def camera_motion_note(observation: Observation) -> str:
    """Sentences on the camera's motion for the log and the report ("" for mask input, or when
    no pixel of any frame moved more than :data:`STILL_PX` and every frame's background
    registered)."""
    registered = observation.camera_registered
    lost = ""
    if registered is not None and not registered.all():
        frames = observation.frame_indices[~registered]
        lost = (f"The background of {len(frames)} of {len(registered)} frames ({_frame_spans(frames)}) did not "
                f"register: it correlates less than {MOTION_MIN_CORRELATION} with the clip's (too little "
                f"texture, or too much of it hidden). " + (
                    "Their move is not measured, and they are left out of the fit (camera move not measured)."
                    if observation.stabilised else
                    "A move of the camera in them would not be seen, and what the model finds there may be the "
                    "camera's motion."))
    if observation.camera_moved_px <= STILL_PX:
        return lost
    size = observation.masks.shape[1:3]
    moves = _frame_moves(observation.camera_motion, size)
    rows = _motion_rows(observation.camera_motion, size)
    shifts, turns = np.linalg.norm(rows[:, :2], axis=1), np.abs(rows[:, 2])
    frame = int(observation.frame_indices[int(np.argmax(moves))])
    line = (f"The camera moved: the background of frame {frame} moved up to {moves.max():.2f} px against the "
            f"clip's, at a corner (over the frames, the image centre's move RMS "
            f"{float(np.sqrt((shifts ** 2).mean())):.2f} px and the turn about the line of sight RMS "
            f"{float(np.sqrt((turns ** 2).mean())):.3f} deg)")
    if observation.stabilised:
        line += "; the frames were moved back before they were segmented (data.segmentation.stabilise)."
    else:
        line += ("; the frames were not moved back (data.segmentation.stabilise=false), and the model "
                 "takes a still camera: what it finds may be the camera's motion.")
    return line + (" " + lost if lost else "")


def _moved_back(image: np.ndarray, matrix: np.ndarray, flags: int) -> np.ndarray:
    """``image`` resampled where the (3, 3) map ``matrix`` sends each pixel (the frame a still
    camera would have taken, when ``matrix`` is the frame's motion), the border replicated."""
    height, width = image.shape[:2]
    return cv2.warpPerspective(image, matrix, (width, height), flags=flags | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)


def stabilised(frames: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """(T, H, W, C) ``frames`` each moved back by its map of (T, 3, 3) ``maps``
    (:func:`camera_motion`), resampled with Lanczos: the frames a still camera would have taken."""
    return np.stack([_moved_back(frame, matrix, cv2.INTER_LANCZOS4) for frame, matrix in zip(frames, maps)])


def unseen_pixels(maps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T, H, W) bool: the pixels of each frame moved back by its map of (T, 3, 3) ``maps``
    (:func:`stabilised`) that the camera did not see in that frame, or that Lanczos drew from
    outside it (within :data:`LANCZOS_REACH_PX` of the frame's edge): the border filled by
    replication."""
    height, width = size
    ones = np.ones((height, width), np.uint8)
    grow = np.ones((2 * LANCZOS_REACH_PX + 1,) * 2, np.uint8)
    seen = np.stack([cv2.erode(cv2.warpPerspective(ones, m, (width, height),
                                                   flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0),
                               grow, borderType=cv2.BORDER_CONSTANT, borderValue=1)
                     for m in maps])
    return seen == 0


def _background_where_unseen(frames: np.ndarray, unseen: np.ndarray) -> np.ndarray:
    """(T, H, W, C) ``frames`` with their (T, H, W) ``unseen`` pixels set to the median over the
    frames that saw that pixel (the background there), so a border a frame did not see reads
    as background rather than as something that moved; a pixel no frame saw keeps its value."""
    band = unseen.any(axis=0)
    if not band.any():
        return frames
    values = frames[:, band].astype(np.float32)  # (T, K, C)
    hidden = unseen[:, band]
    seen_by_some = ~hidden.all(axis=0)
    values[hidden] = np.nan
    median = np.zeros(values.shape[1:], np.float32)
    median[seen_by_some] = np.nanmedian(values[:, seen_by_some], axis=0)
    fill = hidden & seen_by_some[None]
    out = frames.copy()
    part = out[:, band]
    part[fill] = np.clip(np.rint(np.broadcast_to(median, part.shape)[fill]), 0, 255).astype(frames.dtype)
    out[:, band] = part
    return out


def _turn_map(params: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(3, 3) the map ``T(d) K R K^-1`` (scaled to ``[2, 2] = 1``) of a camera with (3, 3)
    intrinsics ``k`` turned by the rotation vector ``params[:3]`` (radians, about its x, y and
    optical axes, x right, y down) and its picture then shifted by ``d = params[3:5]`` (px):
    where a still camera's pixel lies in the frame (:func:`camera_motion`)."""
    h = k @ cv2.Rodrigues(np.asarray(params[:3], float))[0] @ np.linalg.inv(k)
    h[:2] += h[2] * np.asarray(params[3:5], float)[:, None]
    return h / h[2, 2]


def _turn_map_derivatives(params: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(5, 3, 3) the derivatives of :func:`_turn_map` by each of its five parameters (central
    differences: 1e-6 rad, 1e-4 px)."""
    steps = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4])
    out = np.empty((5, 3, 3))
    for i, step in enumerate(steps):
        ahead, back = np.array(params, float), np.array(params, float)
        ahead[i] += step
        back[i] -= step
        out[i] = (_turn_map(ahead, k) - _turn_map(back, k)) / (2 * step)
    return out


def _point_slopes(points: np.ndarray, h: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """(N, 2, K) how far the (N, 3) points ``(x, y, 1)`` move under the (3, 3) map ``h`` per unit
    of each of K parameters whose (K, 3, 3) derivatives of ``h`` are ``slopes``:
    ``d(x', y') = ((dh p)_xy - (x', y') (dh p)_z) / (h p)_z``."""
    moved = points @ h.T  # (N, 3)
    at = moved[:, :2] / moved[:, 2:]
    d = (points @ slopes.transpose(2, 1, 0).reshape(3, -1)).reshape(len(points), 3, len(slopes))
    return (d[:, :2] - at[:, :, None] * d[:, 2:]) / moved[:, 2, None, None]


def _sampled(image: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(N,) float64: the (H, W) float32 ``image`` at the (N, 2) points ``at`` (x, y, px),
    bilinear, the border replicated (``cv2.remap``, whose maps are at most 32767 a side, so
    laid out in rows)."""
    count, row = len(at), 1024
    shape = (-(-count // row), row)
    at_x, at_y = (np.resize(v.astype(np.float32), shape[0] * row).reshape(shape) for v in at.T)
    sampled = cv2.remap(image, at_x, at_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return sampled.reshape(-1)[:count].astype(np.float64)


def _register(reference: np.ndarray, image: np.ndarray, valid: np.ndarray | None, k: np.ndarray,
              params: np.ndarray, active: list[int], finest: int = 0,
              min_correlation: float = MOTION_MIN_CORRELATION) -> tuple[np.ndarray, float, np.ndarray]:
    """(5,) the parameters of :func:`_turn_map` (from ``params``, those listed in ``active``
    fitted) with ``image(W(p)) ~ reference(p)`` for (H, W) float32 images over the ``valid``
    pixels of ``reference`` (all when None), the correlation they reach on the last level run
    (NaN when no level ran), and (K, K) the covariance of the K ``active`` parameters there
    (NaN when no level ran): the sandwich ``(JᵀJ)⁻¹ (Σ_b g_b g_bᵀ) (JᵀJ)⁻¹``, ``g_b`` the sum of
    ``J_i r_i`` over the points of a tile ``b`` of :data:`MOTION_TILE_PX` a side, ``r`` the
    residual between the moved image (scaled by ECC's gain to the reference) and the reference;
    ``params`` as given where the background does not register (that
    correlation is under ``min_correlation``, or not a number). ECC's Gauss-Newton step (Evangelidis and Psarakis, 2008: the
    correlation of the zero-mean images, so a change of exposure does not move the map), its
    Jacobian fixed per level from the reference's gradient, on the :data:`MOTION_POINTS`
    steepest valid pixels; coarse to fine on a Gaussian pyramid (halved while the smaller side
    stays at least :data:`MOTION_PYRAMID_MIN_PX`), so a move of several pixels is found from none;
    ``finest`` levels at the bottom are left out (a coarser, cheaper estimate). A level stops
    when a step moves no corner by more than :data:`MOTION_STEP_PX` of its pixels, after
    :data:`MOTION_ITERATIONS` steps, or where a step is undefined; one whose steps lowered the
    correlation by more than :data:`MOTION_SCORE_DROP` keeps its start (on a background with too
    little texture to register, the steps run off)."""
    levels = [(reference, image, np.ones(reference.shape, bool) if valid is None else valid)]
    while min(levels[-1][0].shape) >= 2 * MOTION_PYRAMID_MIN_PX:
        ref, img, mask = levels[-1]
        levels.append((cv2.pyrDown(ref), cv2.pyrDown(img),
                       cv2.resize(mask.astype(np.uint8), (img.shape[1] // 2 + img.shape[1] % 2,
                                                          img.shape[0] // 2 + img.shape[0] % 2),
                                  interpolation=cv2.INTER_NEAREST) > 0))
    given, params, score = np.array(params, float), np.array(params, float), float("nan")
    covariance = np.full((len(active), len(active)), np.nan)
    for level in range(len(levels) - 1, min(finest, len(levels) - 1) - 1, -1):
        ref, img, mask = levels[level]
        height, width = ref.shape
        scale = np.diag([2.0 ** level, 2.0 ** level, 1.0])  # a pixel p of this level is the pixel scale p of the finest
        down = np.linalg.inv(scale)
        h = down @ _turn_map(params, k) @ scale
        # the Jacobian, fixed for the level: the reference's gradient (what the frame's is, where
        # they match) times how each parameter moves each point (_point_slopes), on the
        # MOTION_POINTS steepest valid pixels that the start maps MOTION_MARGIN_PX inside the frame
        grad_x = cv2.Sobel(ref, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        grad_y = cv2.Sobel(ref, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        steepness = np.where(mask, grad_x ** 2 + grad_y ** 2, -1.0).reshape(-1)
        chosen = np.flatnonzero(steepness >= 0)
        if len(chosen) > MOTION_POINTS:
            chosen = np.argpartition(steepness, -MOTION_POINTS)[-MOTION_POINTS:]
        rows, cols = np.divmod(chosen, width)
        points = np.column_stack([cols, rows, np.ones(len(cols))])  # (N, 3)
        x, y = _mapped(h[None], points)[0].T
        keep = ((x >= MOTION_MARGIN_PX) & (x <= width - 1 - MOTION_MARGIN_PX)
                & (y >= MOTION_MARGIN_PX) & (y <= height - 1 - MOTION_MARGIN_PX))
        if keep.sum() < 10 * len(active):
            break
        rows, cols, points, x, y = rows[keep], cols[keep], points[keep], x[keep], y[keep]
        grad_x, grad_y = grad_x[rows, cols].astype(np.float64), grad_y[rows, cols].astype(np.float64)
        target = ref[rows, cols].astype(np.float64)
        target -= target.mean()
        moves = _point_slopes(points, h, down @ _turn_map_derivatives(params, k)[active] @ scale)
        jacobian = grad_x[:, None] * moves[:, 0] + grad_y[:, None] * moves[:, 1]
        hessian = jacobian.T @ jacobian
        try:
            inverse = np.linalg.inv(hessian)
        except np.linalg.LinAlgError:
            break
        target_projection = jacobian.T @ target
        corners = _corners(ref.shape)

        def centred(h):
            values = _sampled(img, _mapped(h[None], points)[0])
            return values - values.mean()

        def agreement(warped):  # ECC's criterion, the correlation of the zero-mean values
            return float(target @ warped) / max(float(np.linalg.norm(target) * np.linalg.norm(warped)), 1e-12)

        warped = centred(h)
        start, start_score, start_warped = params.copy(), agreement(warped), warped
        for _ in range(MOTION_ITERATIONS):
            image_projection = jacobian.T @ warped
            solved = inverse @ image_projection
            denominator = target @ warped - target_projection @ solved
            if not denominator > 0:
                break
            gain = (warped @ warped - image_projection @ solved) / denominator  # ECC's lambda
            params[active] += inverse @ (gain * target_projection - image_projection)
            before, h = h, down @ _turn_map(params, k) @ scale
            warped = centred(h)
            if np.abs(_mapped(h[None], corners) - _mapped(before[None], corners)).max() < MOTION_STEP_PX:
                break
        score = agreement(warped)
        if not score >= start_score - MOTION_SCORE_DROP:  # the steps ran off: the level keeps its start
            params, score, warped = start, start_score, start_warped
        gain = float(warped @ target) / max(float(target @ target), 1e-12)  # the image ~ gain x the reference
        residual = warped / gain - target if gain > 0 else np.full_like(target, np.nan)
        # the sandwich (JᵀJ)⁻¹ (Σ_b g_b g_bᵀ) (JᵀJ)⁻¹ over tiles b of MOTION_TILE_PX, g_b a tile's
        # summed J_i r_i: the residuals of neighbouring pixels are correlated (the codec's blocks, blur)
        tile = (rows // MOTION_TILE_PX) * (width // MOTION_TILE_PX + 1) + cols // MOTION_TILE_PX
        scores = np.stack([np.bincount(tile, jacobian[:, i] * residual) for i in range(len(active))], 1)
        covariance = inverse @ (scores.T @ scores) @ inverse
    return (params if score >= min_correlation else given), score, covariance


class CameraMotion(NamedTuple):
    """What :func:`camera_motion` found.

    Attributes:
        maps: (T, 3, 3) each frame's map of a still camera's pixel to the frame's.
        correlation: (T,) how well each frame's background, moved back by its map, correlates
            with the clip's on the last pass (NaN where nothing could be compared).
        registered: (T,) bool, the frames whose correlation reached the floor on the last pass;
            another keeps the map of the pass before (the identity after one pass): its move is
            not measured.
        sigma_px: (T, 4) the standard error of where each frame's map puts each corner of a
            still frame (px, the root of the trace of its 2 x 2 covariance; NaN where nothing
            was compared), from the last pass's Gauss-Newton (:func:`_register`) times
            :data:`MOTION_SIGMA_FACTOR`.
        chi2: (T,) each frame's fitted parameters, about the clip's typical ones, weighed by
            their inverse covariance (times the factor squared): about ``dof`` for a still
            camera (NaN where nothing was compared).
        dof: the parameters fitted per frame (5 with a camera, 3 without).
        passes: how many passes ran (:func:`camera_motion`).
    """

    maps: np.ndarray
    correlation: np.ndarray
    registered: np.ndarray
    sigma_px: np.ndarray
    chi2: np.ndarray
    dof: int
    passes: int


def camera_motion(frames: np.ndarray, camera: Camera | None = None, max_passes: int = MOTION_MAX_PASSES,
                  min_correlation: float = MOTION_MIN_CORRELATION) -> CameraMotion:
    """How each frame's background moved: (T, 3, 3) maps of (T, H, W, 3) uint8 BGR ``frames``
    against the clip's background, so that a still camera's pixel ``p = (x, y, 1)`` lies at
    ``H p`` (divided by its third entry) in the frame, taken about the frames' typical map (a
    still camera reads the identity), with each frame's correlation, whether it reached
    ``min_correlation`` (a frame that does not, on a background with too little texture, keeps
    the map it had) and its standard errors (:class:`CameraMotion`). Each map is a turn of the camera about its three axes seen
    through its intrinsics, ``K R K^-1``, and a shift of the picture (:func:`_turn_map`): what a
    small turn of a camera held in the hand does to a far background, exact for any axis (a pan
    or tilt stretches the picture's edges), and a shift for what moves the picture as a whole.
    Without ``camera`` the pan and tilt are not fitted: the map is a shift and a turn about the
    image centre. A zoom, and a move that shows parallax, are not measured.
    :func:`_motion_rows` reads a map's move and turn at the image centre.

    Each pass moves every frame's grey levels back by the motion so far (:func:`stabilised`),
    takes their median as the reference, and registers each frame against it from its current
    map (:func:`_register`). The first pass stops at the pyramid's second level, as it only
    sharpens that median and finds the object. From the second pass on the object is left
    out: pixels more than :data:`MOTION_OBJECT_DIFF` grey levels off the median, grown by
    :data:`MOTION_OBJECT_GROW_PX`, are masked, and in the frame they take the median's value
    seen through the frame's map; passes run until one moves no frame's corner more than
    :data:`MOTION_SETTLED_PX` against the one before, at most ``max_passes`` in all (against a
    plain wall the object drags the first pass's map, and one more pass pulls it back). The
    typical map is that of the median parameters. The
    pyramid's coarsest level sets how far a move can be found: a few pixels on a 160 x 120
    clip, more on larger frames (experiments/discover/HISTORY.md, *A camera that is not quite
    still*, *Taking out a turn about the line of sight*, *A registration by the homography*,
    *Passes until the maps settle*)."""
    height, width = frames.shape[1:3]
    if camera is None:
        k = np.array([[width, 0.0, (width - 1) / 2], [0.0, width, (height - 1) / 2], [0.0, 0.0, 1.0]])
        active = [2, 3, 4]  # a turn about the image centre and a shift: K's focal length does not enter
    else:
        k, active = np.asarray(camera.K, float), [0, 1, 2, 3, 4]
    grey = np.stack([cv2.cvtColor(f, cv2.COLOR_BGR2GRAY).astype(np.float32) for f in frames])
    params, correlation = np.zeros((len(grey), 5)), np.full(len(grey), np.nan)
    covariance = np.full((len(grey), len(active), len(active)), np.nan)
    grow = np.ones((2 * MOTION_OBJECT_GROW_PX + 1,) * 2, np.uint8)
    corners = _corners((height, width))

    def settled_maps(params):  # each frame's map about the typical one's
        maps = np.stack([_turn_map(p, k) for p in params]) @ np.linalg.inv(_turn_map(np.median(params, axis=0), k))
        return maps / maps[:, 2:, 2:]

    before = None
    for step in range(max_passes):
        maps = np.stack([_turn_map(p, k) for p in params])
        moved = np.stack([_moved_back(g, m, cv2.INTER_LINEAR) for g, m in zip(grey, maps)])
        reference = np.median(moved, axis=0).astype(np.float32)
        for t in range(len(grey)):
            still, image = None, grey[t]
            if step > 0:
                changed = cv2.dilate((np.abs(moved[t] - reference) > MOTION_OBJECT_DIFF).astype(np.uint8), grow)
                still = changed == 0
                in_frame = cv2.warpPerspective(changed, maps[t], (width, height), flags=cv2.INTER_NEAREST) > 0
                seen = cv2.warpPerspective(reference, maps[t], (width, height), flags=cv2.INTER_LINEAR,
                                           borderMode=cv2.BORDER_REPLICATE)
                image = np.where(in_frame, seen, grey[t]).astype(np.float32)
            params[t], correlation[t], covariance[t] = _register(
                reference, image, still, k, params[t], active, finest=1 if step == 0 else 0,
                min_correlation=min_correlation)
        after = settled_maps(params)
        if step > 0 and np.abs(_mapped(after, corners) - _mapped(before, corners)).max() <= MOTION_SETTLED_PX:
            break
        before = after
    typical = np.median(params, axis=0)
    maps = after
    covariance = covariance * MOTION_SIGMA_FACTOR ** 2
    sigma = np.full((len(grey), 4), np.nan)
    chi2 = np.full(len(grey), np.nan)
    for t in range(len(grey)):
        if np.isfinite(covariance[t]).all():
            slopes = _point_slopes(corners, _turn_map(params[t], k), _turn_map_derivatives(params[t], k)[active])
            sigma[t] = np.sqrt(np.maximum(np.einsum("cik,kl,cil->c", slopes, covariance[t], slopes), 0.0))
            apart = (params[t] - typical)[active]
            try:
                chi2[t] = float(apart @ np.linalg.solve(covariance[t], apart))
            except np.linalg.LinAlgError:
                pass
    return CameraMotion(maps, correlation, correlation >= min_correlation, sigma, chi2, len(active), step + 1)


# --------------------------------------------------------------------------------------
# The transfer curve a file names
# --------------------------------------------------------------------------------------

# ITU-T H.273 transfer characteristics, the code that an MP4/MOV 'colr' box, an H.264 stream's
# VUI and a PNG's cICP chunk carry: those SegmentationSettings decodes, and names of some it does not
_H273_DECODED = {1: "bt709", 6: "bt709", 14: "bt709", 15: "bt709", 13: "srgb", 8: "linear", 18: "hlg"}
_H273_UNDECODED = {4: "gamma 2.2", 5: "gamma 2.8", 7: "SMPTE 240M", 9: "logarithmic 100:1",
                   10: "logarithmic 316:1", 11: "IEC 61966-2-4", 12: "BT.1361", 16: "PQ (SMPTE ST 2084)",
                   17: "SMPTE ST 428-1"}
_MP4_SUFFIXES = (".mp4", ".m4v", ".mov", ".3gp")
_MP4_PATH = (b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stsd")
_VISUAL_ENTRY_HEADER = 78  # bytes of a VisualSampleEntry before its child boxes (ISO/IEC 14496-12)
_H264_HIGH_PROFILES = (100, 110, 122, 244, 44, 83, 86, 118, 128, 138, 139, 134, 135)


def _box_header(head: bytes) -> tuple[int, bytes, int]:
    """``(size, type, header length)`` of the ISO base media box whose first (up to 16) bytes are
    ``head``; size 0 means "to the end"."""
    size, kind = int.from_bytes(head[:4], "big"), head[4:8]
    return (int.from_bytes(head[8:16], "big"), kind, 16) if size == 1 else (size, kind, 8)


def _iso_boxes(data: bytes):
    """Yield ``(type, payload)`` of the ISO base media boxes laid end to end in ``data``."""
    i = 0
    while i + 8 <= len(data):
        size, kind, head = _box_header(data[i:i + 16])
        size = size or len(data) - i
        if size < head:
            return
        yield kind, data[i + head:i + size]
        i += size


def _read_moov(path: Path) -> bytes | None:
    """The payload of an MP4/MOV file's top-level 'moov' box, seeking past the others (media data)."""
    with open(path, "rb") as file:
        while len(head := file.read(16)) >= 8:
            size, kind, length = _box_header(head)
            file.seek(length - len(head), 1)  # back to the payload's start
            if kind == b"moov":
                return file.read(size - length if size else -1)
            if size < length:
                return None
            file.seek(size - length, 1)
    return None


class _Bits:
    """An H.264 RBSP read bit by bit (fixed-width and Exp-Golomb fields)."""

    def __init__(self, nal: bytes):
        rbsp, zeros = bytearray(), 0
        for byte in nal:  # drop the emulation prevention bytes (00 00 03 -> 00 00)
            if zeros >= 2 and byte == 3:
                zeros = 0
                continue
            rbsp.append(byte)
            zeros = zeros + 1 if byte == 0 else 0
        self.bits, self.at = "".join(f"{b:08b}" for b in rbsp), 0

    def u(self, n: int) -> int:
        if self.at + n > len(self.bits):
            raise EOFError("the parameter set ends early")
        value = int(self.bits[self.at:self.at + n], 2) if n else 0
        self.at += n
        return value

    def ue(self) -> int:
        zeros = 0
        while self.u(1) == 0:
            zeros += 1
        return (1 << zeros) - 1 + self.u(zeros)

    def se(self) -> int:
        k = self.ue()
        return (k + 1) // 2 if k % 2 else -(k // 2)


def _h264_sps_transfer(nal: bytes) -> int | None:
    """The transfer code of an H.264 sequence parameter set's VUI (ITU-T H.264 7.3.2.1.1, E.1.1),
    None where it carries no colour description."""
    bits = _Bits(nal[1:])  # past the NAL header
    profile = bits.u(8)
    bits.u(16)  # constraint flags, level
    bits.ue()  # seq_parameter_set_id
    if profile in _H264_HIGH_PROFILES:
        chroma = bits.ue()
        if chroma == 3:
            bits.u(1)
        bits.ue(), bits.ue(), bits.u(1)  # bit depths, qpprime_y_zero_transform_bypass
        if bits.u(1):  # seq_scaling_matrix_present
            for i in range(8 if chroma != 3 else 12):
                if bits.u(1):
                    last = following = 8
                    for _ in range(16 if i < 6 else 64):
                        if following:
                            following = (last + bits.se() + 256) % 256
                        last = following or last
    bits.ue()  # log2_max_frame_num_minus4
    order = bits.ue()
    if order == 0:
        bits.ue()
    elif order == 1:
        bits.u(1), bits.se(), bits.se()
        for _ in range(bits.ue()):
            bits.se()
    bits.ue(), bits.u(1), bits.ue(), bits.ue()  # max_num_ref_frames, gaps, width, height in macroblocks
    if not bits.u(1):  # frame_mbs_only
        bits.u(1)
    bits.u(1)  # direct_8x8_inference
    if bits.u(1):  # frame_cropping
        bits.ue(), bits.ue(), bits.ue(), bits.ue()
    if not bits.u(1):  # vui_parameters_present
        return None
    if bits.u(1) and bits.u(8) == 255:  # aspect ratio info, extended SAR
        bits.u(32)
    if bits.u(1):  # overscan_info_present
        bits.u(1)
    if not bits.u(1):  # video_signal_type_present
        return None
    bits.u(4)  # video_format, video_full_range
    if not bits.u(1):  # colour_description_present
        return None
    bits.u(8)  # colour_primaries
    return bits.u(8)


def _mp4_transfer(path: Path) -> tuple[int | None, str]:
    """The transfer code an MP4/MOV file names for its first video track, and where it was read:
    the sample entry's 'colr' box (nclx, or QuickTime's nclc), else its H.264 'avcC' sequence
    parameter set's VUI. ``(None, why)`` where neither names one."""
    moov = _read_moov(path)
    if moov is None:
        return None, "the file has no 'moov' box"

    def entries(data: bytes, depth: int):
        """The sample entries of every track's 'stsd' box, each as ``{child type: payload}``."""
        for kind, payload in _iso_boxes(data):
            if kind == _MP4_PATH[depth] == b"stsd":
                for _, entry in _iso_boxes(payload[8:]):  # past version, flags and the entry count
                    yield dict(_iso_boxes(entry[_VISUAL_ENTRY_HEADER:]))
            elif kind == _MP4_PATH[depth] == b"mdia":
                handler = dict(_iso_boxes(payload)).get(b"hdlr", b"")
                if handler[8:12] in (b"vide", b""):  # a video track's media (or one that does not say)
                    yield from entries(payload, depth + 1)
            elif kind == _MP4_PATH[depth]:
                yield from entries(payload, depth + 1)

    for children in entries(moov, 1):
        colr = children.get(b"colr", b"")
        if colr[:4] in (b"nclx", b"nclc") and len(colr) >= 10:
            return int.from_bytes(colr[6:8], "big"), "'colr' box"
        avcc = children.get(b"avcC", b"")
        if len(avcc) > 8 and avcc[5] & 0x1F:
            try:
                return _h264_sps_transfer(avcc[8:8 + int.from_bytes(avcc[6:8], "big")]), "H.264 stream's VUI"
            except EOFError:
                return None, "H.264 stream's parameter set, which ends early"
    return None, "no video track with a 'colr' box or an H.264 'avcC' box"


def _png_transfer(path: Path) -> tuple[int | None, str]:
    """The transfer code a PNG's chunks name before its image data: cICP (H.273), sRGB (13), or
    gAMA 1.0 (8) or 1/2.2 (13, the sRGB curve's approximation); -1 for another gAMA.
    ``(None, why)`` where none is there."""
    with open(path, "rb") as file:
        data = file.read(1 << 20)
    i = 8  # past the signature
    while i + 8 <= len(data):
        length, kind = int.from_bytes(data[i:i + 4], "big"), data[i + 4:i + 8]
        body = data[i + 8:i + 8 + length]
        if kind == b"cICP" and length >= 2:
            return body[1], "PNG's cICP chunk"
        if kind == b"sRGB":
            return 13, "PNG's sRGB chunk"
        if kind == b"gAMA" and length == 4:
            gamma = int.from_bytes(body, "big") / 100000.0
            if abs(gamma - 1.0) < 0.01:
                return 8, "PNG's gAMA chunk (1.0)"
            if abs(gamma - 1 / 2.2) < 0.01:
                return 13, f"PNG's gAMA chunk ({gamma:.5f}, the sRGB curve's approximation)"
            return -1, f"PNG's gAMA chunk ({gamma:.5f})"
        if kind in (b"IDAT", b"IEND"):
            break
        i += 12 + length
    return None, "the PNG has no cICP, sRGB or gAMA chunk"


def stored_transfer(path: str | Path) -> tuple[str, str]:
    """The transfer curve a recording's file says its pixel values are stored through.

    Args:
        path: a video file or a folder of images (its first image is read).

    Returns:
        ``(transfer, note)``: one of ``TRANSFERS`` other than ``"auto"``, and a sentence on where
        it came from. MP4/MOV files: the colour tag of the first video track ('colr' box, else
        an H.264 stream's VUI); PNG: its cICP, sRGB or gAMA chunk; JPEG: ``"srgb"`` (JFIF and Exif
        store sRGB). ``"linear"`` where the file names no curve (torchfit's own recordings name
        none) or is of a kind whose tags are not read.

    Raises:
        ValueError: the file names a curve that torchfit does not decode (PQ, a pure gamma, ...).
    """
    path = Path(path)
    images = _list_images(path) if path.is_dir() else []
    first = images[0] if images else path
    suffix = first.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return "srgb", f"{first.name}: JPEG stores sRGB"
    if suffix in _MP4_SUFFIXES:
        code, where = _mp4_transfer(first)
    elif suffix == ".png":
        code, where = _png_transfer(first)
    else:
        return "linear", f"{first.name}: colour tags are read from MP4/MOV, PNG and JPEG files only; read as linear"
    if code is None or code == 2:  # 2: unspecified
        named = f"the {where} names it unspecified" if code == 2 else where
        return "linear", f"{first.name}: no transfer curve named ({named}); read as linear"
    if code in _H273_DECODED:
        return _H273_DECODED[code], f"{first.name}: transfer {code} ({_H273_DECODED[code]}) from the {where}"
    label = f"transfer {code} ({_H273_UNDECODED.get(code, 'a code torchfit does not know')})" if code >= 0 else "a gamma"
    raise ValueError(f"{str(first)!r}: the {where} names {label}, which torchfit does not decode; set the "
                     f"segmentation's transfer to one of {', '.join(t for t in TRANSFERS if t != 'auto')} "
                     "to read it as that")


# --------------------------------------------------------------------------------------
# Segmentation
# --------------------------------------------------------------------------------------


def _estimate_background(frames: np.ndarray, settings: SegmentationSettings) -> np.ndarray:
    """(H, W, 3) float32 background from (T, H, W, 3) uint8 BGR frames."""
    step = max(1, math.ceil(len(frames) / settings.max_background_frames))
    sample = frames[::step]
    if settings.method == "median":
        return np.median(sample, axis=0).astype(np.float32)
    subtractor = cv2.createBackgroundSubtractorMOG2(history=len(sample), detectShadows=False)
    for frame in sample:
        subtractor.apply(frame)
    return subtractor.getBackgroundImage().astype(np.float32)


def _morph(masks: np.ndarray, op: str, radius: int) -> np.ndarray:
    """Batched binary morphology with a (2r+1)^2 square on (T, H, W) bool masks.

    A flat square element makes dilation a max-pool and erosion a min-pool, which on CPU is
    ~5x faster than ``kornia.morphology`` (same result, outside pixels ignored).
    """
    if radius == 0:
        return masks
    images = torch.from_numpy(masks.astype(np.float32))[:, None]  # (T, 1, H, W)
    size = 2 * radius + 1

    def dilate(x):
        return torch.nn.functional.max_pool2d(x, size, stride=1, padding=radius)

    def erode(x):
        return -dilate(-x)

    steps = {"dilation": (dilate,), "erosion": (erode,), "opening": (erode, dilate),
             "closing": (dilate, erode)}[op]
    for step in steps:
        images = step(images)
    return images[:, 0].numpy() > 0.5


def _components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels (H, W) and areas (N,) of the 8-connected components, background excluded."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return labels, stats[1:, cv2.CC_STAT_AREA]


def _largest(mask: np.ndarray) -> np.ndarray:
    labels, areas = _components(mask)
    if len(areas) == 0:
        return np.zeros_like(mask, bool)
    return labels == 1 + int(np.argmax(areas))


def _decode(values: np.ndarray, transfer: str) -> np.ndarray:
    """Pixel values (any shape, 0..255) as linear light on the same 0..255 scale, float32:
    unchanged for ``transfer="linear"`` (and ``"auto"``: frames without a file to name a curve, as
    :func:`_segment` is given them, are taken as they are), else the inverse of the named curve."""
    if transfer in ("linear", "auto"):
        return values.astype(np.float32)
    if values.dtype == np.uint8:  # a table of the 256 codes
        return _decode(np.arange(256, dtype=np.float64), transfer).astype(np.float32)[values]
    c = np.clip(values.astype(np.float64) / 255.0, 0.0, 1.0)
    if transfer == "srgb":
        light = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    elif transfer == "hlg":  # BT.2100 hybrid log-gamma: sqrt(3 L) below L = 1/12, a ln(12 L - b) + c above
        a, b, k = 0.17883277, 0.28466892, 0.55991073
        light = np.where(c <= 0.5, c * c / 3.0, (np.exp((np.maximum(c, 0.5) - k) / a) + b) / 12.0)
    elif transfer == "bt709":  # the camera's curve 4.5 L below L = 0.018, 1.099 L^0.45 - 0.099 above
        light = np.where(c < 0.081, c / 4.5, ((c + 0.099) / 1.099) ** (1.0 / 0.45))
    else:
        raise ValueError(f"transfer must be one of {TRANSFERS}, got {transfer!r}")
    return (255.0 * light).astype(np.float32)


def _luma_chroma(bgr: np.ndarray, chroma_weight: float) -> np.ndarray:
    """(..., 3) BGR -> (..., 3) float32 [Y, w (B - Y), w (R - Y)]: linear, so the mixing model holds."""
    bgr = bgr.astype(np.float32)
    luma = 0.114 * bgr[..., 0] + 0.587 * bgr[..., 1] + 0.299 * bgr[..., 2]
    return np.stack([luma, chroma_weight * (bgr[..., 0] - luma), chroma_weight * (bgr[..., 2] - luma)], -1)


def _local_contrast(background: np.ndarray, albedo: np.ndarray, coverage: np.ndarray, shaded: np.ndarray,
                    weight: np.ndarray, radius: float, linear: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The object-background colour difference ``F - B`` with the shading fitted locally.

    Args: as :func:`_local_shading_coverage`.

    Returns:
        (H, W, 3) ``F - B`` in luma/chroma, and (H, W) bool where the shading has support.

    The local shading minimises ``sum_k g(x - k) w_k (u_k - a_k s)^2``, so
    ``s(x) = G*(w a u) / G*(w a^2)``: mixed pixels count in proportion to their coverage, and
    the background (``a ~ 0``) not at all. Where the near neighbourhood has too little
    support, a 4x wider one is used. ``linear``: the shading is a plane in the window,
    ``s(x) + g.(k - x)`` (:func:`_local_linear_shading`), where a constant borrows the brighter
    inside of a limb that darkens toward its edge.
    """
    a = np.clip(coverage, 0.0, 1.0)
    w = weight.astype(np.float32)
    numerator, denominator = (w * a * shaded).astype(np.float32), (w * a * a).astype(np.float32)
    near = [cv2.GaussianBlur(x, (0, 0), radius) for x in (numerator, denominator)]
    wide = [cv2.GaussianBlur(x, (0, 0), 4.0 * radius) for x in (numerator, denominator)]
    shading = np.where(near[1] > 0.02, near[0] / np.maximum(near[1], 1e-9),
                       wide[0] / np.maximum(wide[1], 1e-9))
    if linear:  # solved only over the support's box, widened by the blur's reach (4 sigma)
        rows, cols = np.nonzero(w * a > 0)
        if len(rows):
            margin = int(math.ceil(4.0 * radius)) + 2
            box = (slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
                   slice(max(cols.min() - margin, 0), cols.max() + margin + 1))
            plane = shading.copy()
            plane[box] = _local_linear_shading((w * a * a)[box], (w * a * shaded)[box], radius, shading[box])
            shading = np.where(near[1] > 0.02, plane, shading)
    return shading[..., None] * albedo - background, wide[1] > 1e-3


# _local_linear_shading: the gradient's ridge, in units of a full window's spread (weight x radius^2)
SHADING_GRADIENT_RIDGE = 0.1


def _local_linear_shading(weight: np.ndarray, weighted_target: np.ndarray, radius: float,
                          constant: np.ndarray) -> np.ndarray:
    """(H, W) the shading's local-linear fit: at each pixel ``x`` the ``s`` of the plane
    ``s + g.(k - x)`` that minimises ``sum_k G(x - k) W_k (s_k - s - g.(k - x))^2``, with
    ``W = w a^2`` ((H, W) ``weight``) and ``W s_k = w a u`` ((H, W) ``weighted_target``), ``G`` a
    Gaussian of sigma ``radius``. Its normal equations come from Gaussian-blurred moments of the
    pixel coordinates (about the array's centre, float64; the caller passes the box its support
    lies in); the gradient has a ridge of
    ``SHADING_GRADIENT_RIDGE`` times a full window's spread, so a window with one-sided or thin
    support tends to the local constant. Clipped to [0, 2 x ``constant``] (the local-constant fit),
    as a plane extrapolated past its support can run off."""
    height, width = weight.shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    u -= width / 2
    v -= height / 2
    weight, weighted_target = weight.astype(np.float64), weighted_target.astype(np.float64)

    def blur(x):
        return cv2.GaussianBlur(x, (0, 0), radius)

    m0, mu, mv = blur(weight), blur(weight * u), blur(weight * v)
    muu, muv, mvv = blur(weight * u * u), blur(weight * u * v), blur(weight * v * v)
    n0, nu, nv = blur(weighted_target), blur(weighted_target * u), blur(weighted_target * v)
    ridge = SHADING_GRADIENT_RIDGE * m0 * radius**2
    # moments about each pixel x: sum W d, sum W d d^T, sum W d s with d = k - x
    du, dv = mu - u * m0, mv - v * m0
    duu = muu - 2 * u * mu + u * u * m0 + ridge
    dvv = mvv - 2 * v * mv + v * v * m0 + ridge
    duv = muv - u * mv - v * mu + u * v * m0
    ru, rv = nu - u * n0, nv - v * n0
    system = np.stack([np.stack([m0, du, dv], -1), np.stack([du, duu, duv], -1), np.stack([dv, duv, dvv], -1)], -2)
    rhs = np.stack([n0, ru, rv], -1)
    solved = np.linalg.solve(system + 1e-12 * np.eye(3), rhs[..., None])[..., 0, 0]
    return np.clip(solved, 0.0, 2.0 * constant).astype(np.float32)


def _local_shading_coverage(diff: np.ndarray, background: np.ndarray, albedo: np.ndarray,
                            coverage: np.ndarray, shaded: np.ndarray, weight: np.ndarray,
                            fallback: np.ndarray, radius: float, linear: bool = False) -> np.ndarray:
    """Coverage with the shading fitted over a neighbourhood (step 3b of the module docstring).

    Args:
        diff: (H, W, 3) ``I - B`` in luma/chroma.
        background: (H, W, 3) ``B`` in luma/chroma.
        albedo: (3,) unit albedo direction ``A``.
        coverage: (H, W) per-pixel coverage ``a`` of the 2-unknown fit.
        shaded: (H, W) per-pixel ``u = a s`` of the same fit.
        weight: (H, W) bool, pixels whose ``(a, u)`` are trusted (well posed, near the object).
        fallback: (H, W) coverage to keep where the shading has no support or ``F ~ B``.
        radius: Gaussian sigma (pixels) of the neighbourhood.
        linear: the shading a plane in the neighbourhood, not a constant (:func:`_local_contrast`).

    Returns:
        (H, W) float32 coverage: the projection ``(I - B).(F - B) / |F - B|^2`` with ``F - B``
        from :func:`_local_contrast`.
    """
    contrast, support = _local_contrast(background, albedo, coverage, shaded, weight, radius, linear)
    contrast2 = (contrast**2).sum(-1)
    projected = (diff * contrast).sum(-1) / np.maximum(contrast2, 1e-6)
    supported = support & (contrast2 > 100.0)  # |F - B| > 10 grey levels
    return np.where(supported, projected, fallback).astype(np.float32)


# SegmentationSettings.albedo_passes take the albedo from pixels covered at least this much (when
# at least ALBEDO_MIN_PIXELS are)
PURE_COVERAGE = 0.9
ALBEDO_MIN_PIXELS = 10


def _background_terms(background: np.ndarray, albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The background's part of :func:`_two_unknown`'s normal equations, each (...,) for (..., 3)
    ``B`` and a (3,) albedo ``A``: ``A.B``, ``|B|^2`` and their determinant ``|B|^2 sin^2(angle(A, B))``."""
    a_dot_b = background @ albedo
    b_dot_b = (background**2).sum(-1)
    return a_dot_b, b_dot_b, b_dot_b - a_dot_b**2


def _two_unknown(diff: np.ndarray, background: np.ndarray, albedo: np.ndarray,
                 terms: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The per-pixel 2-unknown fit ``D = u A - a B`` (step 3a of the module docstring), its 2x2
    normal equations solved in closed form: coverage ``a`` and ``u = a s``, each (...,), for
    (..., 3) ``D = I - B`` and ``B`` in luma/chroma and a (3,) unit albedo ``A``. ``terms``: the
    :func:`_background_terms` of ``B`` and ``A`` where the caller has them (every frame shares them)."""
    a_dot_b, b_dot_b, det = terms if terms is not None else _background_terms(background, albedo)
    det = np.maximum(det, 1e-6)
    d_dot_a, d_dot_b = diff @ albedo, (diff * background).sum(-1)
    return (a_dot_b * d_dot_a - d_dot_b) / det, (b_dot_b * d_dot_a - a_dot_b * d_dot_b) / det


def _albedo(colours: np.ndarray, coverage: np.ndarray | None) -> np.ndarray:
    """(3,) unit albedo direction: the median direction of (N, 3) object colours in luma/chroma,
    of those whose ``coverage`` (N,) is at least ``PURE_COVERAGE`` when given and enough are.

    A pixel the object only partly covers mixes in the background's colour: on a blurred or
    thin object most eroded "object" pixels do (0.57 is their median coverage on the synthetic
    blurred disc of ``tests/test_video.py``), the median direction tilts toward the background, and every edge pixel then reads more
    coverage than it has (a silhouette too large in proportion to its blur)."""
    if coverage is not None:
        pure = coverage >= PURE_COVERAGE
        if pure.sum() >= ALBEDO_MIN_PIXELS:
            colours = colours[pure]
    colours = colours.astype(np.float32)
    colours = colours / np.maximum(np.linalg.norm(colours, axis=1, keepdims=True), 1e-6)
    albedo = np.median(colours, axis=0)
    return albedo / np.linalg.norm(albedo)


def mask_velocity(masks: np.ndarray) -> np.ndarray:
    """(T, 2) px per frame: the (T, H, W) bool masks' centroids' central differences (one-sided
    at the ends; NaN beside an empty mask, zero for a single frame): the motion as the video
    alone gives it."""
    centre = np.array([np.argwhere(m).mean(0)[::-1] if m.any() else (np.nan, np.nan) for m in masks])
    return np.gradient(centre, axis=0) if len(masks) > 1 else np.zeros((len(masks), 2))


def motion_band(mask: np.ndarray, steps: int, velocity: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels within ``steps`` 4-neighbour steps of an (H, W) bool ``mask``, that
    band then swept half the frame's travel either way along it (``velocity``, (2,) ``(du, dv)``
    px per frame): as far along the motion as the blur of any exposure up to the whole frame
    interval reaches (a moving edge's ramp ends half the exposure's travel past its mid-exposure
    position), and no wider across it."""
    band = ndimage.binary_dilation(mask, iterations=steps)
    half = 0.5 * np.asarray(velocity, np.float64)
    reach = int(math.ceil(np.abs(half).max())) if np.all(np.isfinite(half)) else 0
    if reach == 0:
        return band
    kernel = np.zeros((2 * reach + 1, 2 * reach + 1), np.uint8)
    ends = [(int(round(reach + sign * half[0])), int(round(reach + sign * half[1]))) for sign in (-1, 1)]
    cv2.line(kernel, ends[0], ends[1], 1)
    return cv2.dilate(band.astype(np.uint8), kernel).astype(bool)


def raw_moments(images: np.ndarray) -> np.ndarray:
    """(T, 6) raw moments ``(m00, m10, m01, m20, m11, m02)`` of (T, H, W) non-negative images
    about the image origin, ``u`` the column and ``v`` the row index (float64)."""
    images = np.asarray(images, np.float64)
    u = np.arange(images.shape[2], dtype=np.float64)
    v = np.arange(images.shape[1], dtype=np.float64)
    rows = images.sum(2)  # (T, H)
    row_u = images @ u  # (T, H): sum over each row of a u
    row_uu = images @ (u * u)
    return np.stack((rows.sum(1), row_u.sum(1), rows @ v, row_uu.sum(1), row_u @ v, rows @ (v * v)), -1)


def _segment(frames: np.ndarray, settings: SegmentationSettings,
             undistort: tuple[np.ndarray, np.ndarray] | None = None,
             trusted: np.ndarray | None = None) -> dict:
    """Segment (T, H, W, 3) uint8 BGR frames; returns the arrays that are cached. ``undistort``:
    the camera's undistortion maps (:func:`_undistort_maps`), through which each frame's soft
    coverage is resampled (linearly: a coverage is a fraction, so a point takes the value where
    it was imaged) before its moments are taken; the masks stay as imaged. ``trusted``: (T,)
    bool, the frames the object's colour may be learnt from (all when None): a frame out of place
    against the background (a camera move not measured) differs from it everywhere, and would
    teach the background's colours as the object's; nor is it learnt from a frame whose seed
    (its largest detected region) is more than ``settings.area_jump`` times the median seed."""
    background_bgr = _estimate_background(frames, settings)
    background = _luma_chroma(_decode(background_bgr, settings.transfer), settings.chroma_weight)
    frames = _luma_chroma(_decode(frames, settings.transfer), settings.chroma_weight)
    diff = frames - background  # (T, H, W, 3)
    magnitude = np.sqrt((diff**2).sum(-1))  # (T, H, W)
    centre = float(np.median(magnitude))
    noise = 1.4826 * float(np.median(np.abs(magnitude - centre)))
    threshold = centre + settings.noise_sigmas * max(noise, 1.0)

    detected = _morph(magnitude > threshold, "opening", settings.morph_radius)
    seeds = np.zeros_like(detected)
    seed_areas = np.zeros(len(frames), np.int64)
    second_frac = np.zeros(len(frames), np.float32)
    for t, mask in enumerate(detected):
        labels, areas = _components(mask)
        if len(areas) == 0 or areas.max() < settings.min_area:
            continue
        order = np.argsort(areas)[::-1]
        seeds[t], seed_areas[t] = labels == 1 + order[0], areas[order[0]]
        if len(areas) > 1:
            second_frac[t] = areas[order[1]] / areas[order[0]] if areas[order[1]] >= settings.min_area else 0

    # Albedo direction A of the object from its confident (eroded) pixels in all trusted frames,
    # none from a frame whose seed is more than area_jump times the typical one: a hand before the
    # lens or a flash in one frame would teach its colours as the object's
    trusted = np.ones(len(frames), bool) if trusted is None else trusted.copy()
    if (seed_areas > 0).any():
        trusted &= seed_areas <= settings.area_jump * np.median(seed_areas[seed_areas > 0])
    taught = seeds & trusted[:, None, None]
    core = _morph(taught, "erosion", 1)
    if core.sum() < 10:
        core = taught
    if not core.any():
        return {"masks": seeds, "background": background_bgr, "second_frac": second_frac,
                "coverage_moments": raw_moments(seeds)}
    _, rows, cols = np.nonzero(core)
    colours = frames[core]
    albedo = _albedo(colours, None)
    for _ in range(settings.albedo_passes):
        albedo = _albedo(colours, _two_unknown(diff[core], background[rows, cols], albedo)[0])

    terms = _background_terms(background, albedo)  # the same for every frame
    # |B| sin(angle(A, B)) > well_posed_grey, else the coverage falls back to |D| / contrast
    well_posed = terms[2] > settings.well_posed_grey**2

    region = _morph(seeds, "dilation", 2 * settings.morph_radius + 1)
    steps = settings.band_steps(*frames.shape[1:3])
    seed_velocity = mask_velocity(seeds) if settings.interior_shading else None
    masks = np.zeros_like(seeds)
    covers = {}  # frame -> (H, W) coverage before smoothing and threshold
    for t in range(len(frames)):
        if not seeds[t].any():
            continue
        coverage, shaded = _two_unknown(diff[t], background, albedo, terms)  # u = a s
        contrast = float(np.percentile(magnitude[t][seeds[t]], 90))
        fallback = np.where(well_posed, coverage, magnitude[t] / max(contrast, 1e-6))
        if settings.shading_radius > 0:
            weight = well_posed & region[t] & (coverage > 0.05)
            if settings.interior_shading:  # the seed's inside, beyond any blur's reach: a = 1, u = s = I.A
                inner = ~motion_band(~seeds[t], steps, seed_velocity[t]) & ~well_posed
                coverage, shaded = np.where(inner, 1.0, coverage), np.where(inner, frames[t] @ albedo, shaded)
                weight |= inner
            coverage = _local_shading_coverage(diff[t], background, albedo, coverage, shaded, weight, fallback,
                                               settings.shading_radius, settings.shading_fit == "linear")
        else:
            coverage = fallback
        covers[t] = coverage
        if settings.alpha_smoothing > 0:
            coverage = cv2.GaussianBlur(coverage.astype(np.float32), (0, 0), settings.alpha_smoothing)
        masks[t] = (coverage >= settings.alpha_threshold) & region[t]
    masks = _morph(masks, "closing", settings.morph_radius)
    for t in range(len(frames)):
        if masks[t].any():
            masks[t] = ndimage.binary_fill_holes(_largest(masks[t]))
    velocity = mask_velocity(masks) if settings.coverage_band == "motion" else np.zeros((len(frames), 2))
    cover_moments = np.zeros((len(frames), 6))
    for t in range(len(frames)):
        if masks[t].any():
            near = motion_band(masks[t], steps, velocity[t])
            cover = (np.clip(covers[t], 0.0, 1.0) if settings.coverage_clip else covers[t]) * near
            if undistort is not None:
                cover = cv2.remap(cover.astype(np.float32), *undistort, interpolation=cv2.INTER_LINEAR)
            cover_moments[t] = raw_moments(cover[None])[0]
    return {"masks": masks, "background": background_bgr, "second_frac": second_frac,
            "coverage_moments": cover_moments}


# --------------------------------------------------------------------------------------
# Boxes, flags, undistortion, cache
# --------------------------------------------------------------------------------------


def _boxes(masks: np.ndarray) -> np.ndarray:
    """(T, 4) inclusive ``(x0, y0, x1, y1)`` of (T, H, W) masks; NaN for empty masks."""
    boxes = np.full((len(masks), 4), np.nan)
    for t, mask in enumerate(masks):
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if len(rows):
            boxes[t] = (cols[0], rows[0], cols[-1], rows[-1])
    return boxes


def _flag(masks: np.ndarray, second_frac: np.ndarray, settings: SegmentationSettings,
          unseen: np.ndarray | None = None, unmeasured: np.ndarray | None = None) -> list[str]:
    """One reason per frame, ``""`` for frames fit to use. ``unseen``: (T, H, W) bool, the border
    each frame did not see (:func:`unseen_pixels`; none when None): a mask beside it touches the
    frame's border. ``unmeasured``: (T,) bool, the frames of a clip moved back whose background
    did not register (:class:`CameraMotion`; none when None): where they lie in a still camera is
    not known."""
    areas = masks.sum(axis=(1, 2))
    reasons = []
    for t, mask in enumerate(masks):
        beside_unseen = unseen is not None and bool(
            (cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)[unseen[t]].any())
        if unmeasured is not None and unmeasured[t]:  # first: a frame out of place may lose its object
            reasons.append("camera move not measured")
        elif areas[t] < settings.min_area:
            reasons.append("no object")
        elif mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any() or beside_unseen:
            reasons.append("touches the image border")
        elif second_frac[t] >= settings.second_component_frac:
            reasons.append("several large components")
        else:
            reasons.append("")
    # Area jumps are judged against neighbours (three each side) that passed the checks above.
    clean = [r == "" for r in reasons]
    for t in range(len(masks)):
        neighbours = [areas[s] for s in range(max(t - 3, 0), min(t + 4, len(masks)))
                      if s != t and clean[s]]
        if not clean[t] or not neighbours:
            continue
        ratio = areas[t] / np.median(neighbours)
        if max(ratio, 1.0 / ratio) > settings.area_jump:
            reasons[t] = f"area jumps x{ratio:.2f} vs neighbours"
    return reasons


# Gaussian sigma (pixels) that smooths a binary mask's staircase before it is resampled through the
# undistortion: nearest-neighbour resampling moved each edge by up to half a pixel, coherently
# wherever the map's fractional part drifts slowly (discs of radius 12 px through k1 -0.3, k2 0.1:
# centroid 0.19 px RMS off against 0.12 px this way and 0.06 px drawn undistorted directly;
# tests/test_video.py::test_undistortion_keeps_the_outline_where_it_was).
UNDISTORT_SMOOTHING_PX = 0.7


def _undistort_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (H, W) float32 x and y maps that undistort an image of ``camera`` with its own K
    (each undistorted pixel's place in the distorted image, for ``cv2.remap``)."""
    return cv2.initUndistortRectifyMap(
        camera.K, np.asarray(camera.dist_coeffs, np.float64), None, camera.K,
        (camera.width, camera.height), cv2.CV_32FC1,
    )


def _undistort(masks: np.ndarray, camera: Camera) -> np.ndarray:
    """Undistort (T, H, W) bool masks with the camera's own K: each mask smoothed by a Gaussian of
    ``UNDISTORT_SMOOTHING_PX``, resampled linearly, and thresholded at 0.5 (returns (T, H, W) bool)."""
    maps = _undistort_maps(camera)
    return np.stack([
        cv2.remap(cv2.GaussianBlur(m.astype(np.float32), (0, 0), UNDISTORT_SMOOTHING_PX), *maps,
                  interpolation=cv2.INTER_LINEAR) >= 0.5
        for m in masks
    ])


def _cache_key(path: Path, kind: str, start: int, stop: int | None,
               settings: SegmentationSettings, camera: Camera | None = None) -> str:
    """The segmentation cache's key: the source files, range and settings, the camera's K (the
    camera's motion is registered through it, :func:`camera_motion`) and a distorted camera's
    coefficients (its coverage moments are taken undistorted)."""
    files = _list_images(path) if path.is_dir() else [path]
    stamps = [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in files]
    content = {"version": _CACHE_VERSION, "path": str(path.resolve()), "files": stamps, "kind": kind,
               "start": start, "stop": stop, "settings": asdict(settings)}
    if camera is not None:
        content["K"] = np.asarray(camera.K).tolist()
    if camera is not None and camera.distorted:
        content["lens"] = list(map(float, camera.dist_coeffs))
    payload = json.dumps(content, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def _load_cache(file: Path) -> dict | None:
    if not file.is_file():
        return None
    try:
        with np.load(file) as archive:
            return {name: archive[name] for name in archive.files}
    except (OSError, ValueError, EOFError):  # a damaged cache is recomputed, not fatal
        return None


# --------------------------------------------------------------------------------------
# Main verb
# --------------------------------------------------------------------------------------


def load_observation(
    path: str | Path,
    *,
    kind: str = "auto",
    camera: Camera | str | Path | None = None,
    fps: float | None = None,
    start: int = 0,
    stop: int | None = None,
    cache_dir: str | Path | None = None,
    method: str = "median",
    settings: SegmentationSettings | None = None,
) -> Observation:
    """Masks, boxes and frame flags of the thrown object in a recording.

    Args:
        path: video file, folder of images (sorted by name) or folder of mask PNGs.
        kind: ``"auto"``, ``"video"``, ``"images"`` or ``"masks"``; ``"auto"`` takes a file
            for a video and a folder of single-channel binary images for masks.
        camera: intrinsics or a camera file; frames must have its size, and masks are
            undistorted when it has distortion coefficients.
        fps: frames per second; overrides the video's own, required for folders.
        start, stop: frame range ``start:stop`` of the source (``stop=None``: to the end).
        cache_dir: folder for the segmentation cache (``None``: no cache).
        method: background model, one of ``BACKGROUND_METHODS`` (ignored when ``settings``
            is given).
        settings: all segmentation settings.

    Returns:
        The observation: (T, H, W) masks, (T, 4) boxes, (T,) used flags with reasons.

    Raises:
        ValueError: missing or unreadable input, no frames, nothing moving, a frame size that
            is not the camera's, a bad fps, kind, method or frame range, a transfer curve the
            file names that torchfit does not decode (with ``settings.transfer="auto"``).
    """
    settings = settings or SegmentationSettings(method=method)
    path = Path(path)
    if kind not in KINDS:
        raise ValueError(f'Invalid kind "{kind}". Must be one of {", ".join(KINDS)}')
    if not path.exists():
        raise ValueError(f"input {str(path)!r} does not exist")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or start < 0:
        raise ValueError(f"start must be a non-negative integer, got {start!r}")
    if stop is not None and (not isinstance(stop, (int, np.integer)) or stop <= start):
        raise ValueError(f"stop must be an integer > start = {start}, got {stop!r}")
    if isinstance(camera, (str, Path)):
        camera = Camera.from_file(camera)
    distorted = camera is not None and camera.distorted

    if path.is_dir():
        paths = _list_images(path)
        if not paths:
            raise ValueError(f"folder {str(path)!r} has no frames (no {'/'.join(IMAGE_SUFFIXES)} files)")
        if kind == "video":
            raise ValueError(f"kind='video' needs a file, got the folder {str(path)!r}")
        if kind == "auto":
            kind = "masks" if _looks_like_masks(paths) else "images"
        if fps is None:
            raise ValueError(f"fps must be given for a folder of {kind} ({str(path)!r})")
    else:
        if kind in ("images", "masks"):
            raise ValueError(f"kind={kind!r} needs a folder, got the file {str(path)!r}")
        kind = "video"

    transfer_note = ""
    if kind != "masks":
        if settings.transfer == "auto":
            transfer, transfer_note = stored_transfer(path)
            settings = replace(settings, transfer=transfer)
        else:
            transfer_note = f"transfer {settings.transfer}, as set"

    cache_file = None
    cached = None
    if kind != "masks" and cache_dir is not None:
        cache_file = Path(cache_dir) / f"masks_{_cache_key(path, kind, start, stop, settings, camera)}.npz"
        cached = _load_cache(cache_file)

    background, motion, correlation, sigma, moved_back, unseen = None, None, None, None, False, None
    if kind == "masks":
        masks = _read_mask_folder(paths, start, stop)
        second_frac = np.array([
            (lambda a: a[1] / a[0] if len(a) > 1 and a[1] >= settings.min_area else 0.0)(
                np.sort(_components(m)[1])[::-1]) for m in masks
        ])
        frame_fps = float(fps)
        cover_moments = None  # the masks' own, once undistorted (below)
    elif cached is not None:
        masks, second_frac = cached["masks"].astype(bool), cached["second_frac"]
        background, cover_moments = cached["background"], cached["coverage_moments"]
        frame_fps = float(fps) if fps is not None else float(cached["fps"])
        motion, moved_back = cached["camera_motion"], bool(cached["stabilised"])
        correlation, sigma = cached["camera_correlation"], cached["camera_sigma_px"]
    else:
        if kind == "video":
            frames, file_fps = _read_video(path, start, stop)
        else:
            frames, file_fps = _read_image_folder(paths, start, stop), 0.0
        _check_size(frames.shape[1:3], camera, path)
        found = camera_motion(frames, camera)
        motion, correlation, sigma = found.maps, found.correlation, found.sigma_px.max(1)
        moved_back = settings.stabilise is True or (settings.stabilise == "auto"
                                                    and _largest_move(motion, frames.shape[1:3]) > STILL_PX)
        if moved_back:
            unseen = unseen_pixels(motion, frames.shape[1:3])
            frames = _background_where_unseen(stabilised(frames, motion), unseen)
        segmented = _segment(frames, settings, _undistort_maps(camera) if distorted else None,
                             found.registered if moved_back else None)
        masks, second_frac = segmented["masks"], segmented["second_frac"]
        cover_moments = segmented["coverage_moments"]
        background = cv2.cvtColor(
            np.clip(np.round(segmented["background"]), 0, 255).astype(np.uint8), cv2.COLOR_BGR2RGB)
        if fps is None and not (math.isfinite(file_fps) and file_fps > 0):
            raise ValueError(f"video {str(path)!r} reports no frame rate (fps = {file_fps}); give fps")
        frame_fps = float(fps) if fps is not None else file_fps
        if cache_file is not None:
            cache_file.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(cache_file, masks=masks, second_frac=second_frac,
                                background=background, fps=file_fps, coverage_moments=cover_moments,
                                camera_motion=motion, stabilised=moved_back, camera_correlation=correlation,
                                camera_sigma_px=sigma)
    _check_size(masks.shape[1:3], camera, path)

    if distorted:  # a frame's coverage moments were taken undistorted (_segment)
        masks = _undistort(masks, camera)
    if kind == "masks":
        cover_moments = raw_moments(masks)
    if moved_back:  # a mask that reaches a border the frame did not see may be cut there
        unseen = unseen_pixels(motion, masks.shape[1:3]) if unseen is None else unseen  # None: from the cache
        if distorted:
            unseen = _undistort(unseen, camera)
    # where the camera moved, a frame whose move is not measured has no still place
    unmeasured = ~(correlation >= MOTION_MIN_CORRELATION) if moved_back else None  # NaN: not measured
    reasons = _flag(masks, second_frac, settings, unseen, unmeasured)
    if all(r == "no object" for r in reasons):
        raise ValueError(
            f"nothing moves in {str(path)!r}: no frame has an object "
            f"(all {len(masks)} frames match the background)"
        )
    return Observation(
        masks=masks,
        boxes=_boxes(masks),
        used=np.array([r == "" for r in reasons]),
        reasons=reasons,
        fps=frame_fps,
        frame_indices=np.arange(start, start + len(masks), dtype=np.int64),
        camera=camera,
        source=str(path),
        kind=kind,
        from_cache=cached is not None,
        background=background,
        areas=masks.sum(axis=(1, 2)).astype(np.int64),
        transfer="" if kind == "masks" else settings.transfer,
        transfer_note=transfer_note,
        coverage_moments=cover_moments,
        camera_motion=motion,
        stabilised=moved_back,
        camera_correlation=correlation,
        camera_sigma_px=sigma,
    )


def _check_size(size: tuple[int, int], camera: Camera | None, path: Path) -> None:
    height, width = size
    if camera is not None and (width, height) != (camera.width, camera.height):
        raise ValueError(
            f"frames of {str(path)!r} are {width}x{height} but the camera says "
            f"{camera.width}x{camera.height}"
        )


# --------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------


def contact_sheet(observation: Observation, frames: np.ndarray | None, path: str | Path,
                  n: int = 12, min_tile_width: int = 320) -> Path:
    """Write a PNG grid of ``n`` evenly spaced frames with the mask outline drawn.

    Outlines are green on used frames and red on flagged ones; each tile is labelled with the
    frame number and ``ok`` or the flag reason. Tiny frames are upscaled (nearest neighbour)
    to at least ``min_tile_width`` pixels.

    Args:
        observation: the result of :func:`load_observation`.
        frames: (T, H, W, 3) uint8 RGB or (T, H, W) grey frames matching the observation, or
            None to read them from ``observation.source`` (grey when the source is masks).
        path: PNG file to write (parent folders are created).
        n: number of tiles.

    Returns:
        The path written.
    """
    count = len(observation.masks)
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    picks = np.unique(np.linspace(0, count - 1, min(n, count)).round().astype(int))
    height, width = observation.masks.shape[1:]
    if frames is None:
        if observation.kind == "masks":
            tiles = np.full((len(picks), height, width, 3), 96, np.uint8)
        else:
            tiles = observed_frames(observation, picks)
            camera = observation.camera
            if camera is not None and camera.distorted:
                tiles = np.stack([cv2.undistort(f, camera.K, np.asarray(camera.dist_coeffs))
                                  for f in tiles])
    else:
        frames = np.asarray(frames)
        if frames.shape[:3] != observation.masks.shape:
            raise ValueError(
                f"frames must have shape (T, H, W[, 3]) = {observation.masks.shape}, "
                f"got {frames.shape}"
            )
        tiles = frames[picks]
        if tiles.ndim == 3:
            tiles = np.repeat(tiles[..., None], 3, axis=-1)
    tiles = tiles.astype(np.uint8)

    scale = max(1, math.ceil(min_tile_width / width))
    bar = 22 + 4 * (scale > 1)
    cells = []
    for tile, t in zip(tiles, picks):
        image = cv2.cvtColor(cv2.resize(tile, (width * scale, height * scale),
                                        interpolation=cv2.INTER_NEAREST), cv2.COLOR_RGB2BGR)
        mask = cv2.resize(observation.masks[t].astype(np.uint8), (width * scale, height * scale),
                          interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        used = bool(observation.used[t])
        colour = (0, 255, 0) if used else (0, 0, 255)  # BGR
        cv2.drawContours(image, contours, -1, colour, max(1, scale // 2))
        label = np.zeros((bar, image.shape[1], 3), np.uint8)
        text = f"frame {observation.frame_indices[t]}: " + ("ok" if used else observation.reasons[t])
        cv2.putText(label, text, (4, bar - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
        cells.append(np.vstack([image, label]))
    columns = math.ceil(math.sqrt(len(cells)))
    rows = math.ceil(len(cells) / columns)
    blank = np.zeros_like(cells[0])
    cells += [blank] * (rows * columns - len(cells))
    grid = np.vstack([np.hstack(cells[r * columns:(r + 1) * columns]) for r in range(rows)])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), grid):
        raise ValueError(f"could not write the contact sheet {str(path)!r}")
    return path
