"""What the paper's T-handle experiments share: the shipped recordings, poses, hard silhouettes.

Not a public module; ``tshape_fig3`` and ``predict`` build on it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..render import full_window, render_silhouettes
from ..report import simulate_recording
from ..rotation import rotation_angle
from ..search import Candidates, FitResult, Problem, SearchSettings, candidate_losses
from ..shape import Shape, load_shape

RECORDINGS = ("tshape", "tshape_intermediate", "box_fast", "cylinder", "tshape_small")


@dataclass(frozen=True)
class Recording:
    """A shipped MuJoCo recording and its ground truth.

    Attributes:
        name: folder name under ``torchfit/recordings``.
        folder: the folder.
        shape, camera: the object (density from the truth file) and the intrinsics.
        truth: the parsed truth.json.
        masks: (T, H, W) bool true masks.
    """

    name: str
    folder: Path
    shape: Shape
    camera: Camera
    truth: dict
    masks: np.ndarray

    @property
    def video(self) -> Path:
        return self.folder / "video.mp4"

    def true_rot(self) -> np.ndarray:
        """(T, 3, 3) body->camera rotations of every frame."""
        return np.asarray(self.truth["per_frame"]["R"], np.float64)

    def true_position(self) -> np.ndarray:
        """(T, 3) mesh origins of every frame, camera frame, metres."""
        return np.asarray(self.truth["per_frame"]["position"], np.float64)


def load_recording(name: str) -> Recording:
    """One of the shipped recordings by name.

    Raises:
        ValueError: an unknown name (the message lists the shipped ones).
    """
    if name not in RECORDINGS:
        raise ValueError(f'recording "{name}" is not shipped; must be one of {list(RECORDINGS)}')
    return recording_from_folder(name, Path(str(resources.files("torchfit").joinpath("recordings", name))))


def recording_from_folder(name: str, folder: Path) -> Recording:
    """A recording in the shipped layout (truth.json, mesh.obj, camera.json, masks.npz) from any
    ``folder``: a shipped one, or one made again elsewhere (e.g. through another camera)."""
    truth = json.loads((folder / "truth.json").read_text())
    shape = load_shape(str(folder / "mesh.obj"), density=float(truth["object"]["density"]))
    masks = np.load(folder / "masks.npz")["masks"].astype(bool)
    return Recording(name, folder, shape, Camera.from_file(folder / "camera.json"), truth, masks)


def search_settings(quick: bool, seed: int) -> SearchSettings:
    """The default search, or the quick one of ``configs/search/quick.yaml`` (tests, smoke runs)."""
    if not quick:
        return SearchSettings(seed=seed)
    import yaml

    values = yaml.safe_load(resources.files("torchfit").joinpath("configs", "search", "quick.yaml").read_text())
    values["seed"] = seed  # the file interpolates ${seed}
    return SearchSettings(**values)


def as_result(cands: Candidates, problem: Problem, losses: Tensor | None = None) -> FitResult:
    """A :class:`FitResult` holding given candidates (to reuse :func:`simulate_recording`)."""
    with torch.no_grad():
        state = cands.state(problem.body)
    losses = torch.zeros(len(cands), dtype=state.dtype) if losses is None else losses
    return FitResult(cands, losses.detach(), state.detach(), [], [], {})


def candidate_poses(cands: Candidates, problem: Problem, n_frames: int, first: int, fps: float,
                    index: int = 0) -> tuple[Tensor, Tensor]:
    """Poses of candidate ``index`` at every recording frame: rot (T, 3, 3), trans (T, 3)."""
    with torch.no_grad():
        return simulate_recording(as_result(cands, problem), problem, n_frames, first, fps, index)


def hard_silhouettes(problem: Problem, rot: Tensor, trans: Tensor) -> np.ndarray:
    """(B, T, H, W) bool full-frame silhouettes of poses rot (B, T, 3, 3), trans (B, T, 3)."""
    camera = problem.camera
    batch, frames = rot.shape[:2]
    dtype, device = problem.masks.dtype, problem.masks.device
    rot, trans = rot.to(dtype=dtype, device=device), trans.to(dtype=dtype, device=device)
    with torch.no_grad():
        cover = render_silhouettes(problem.mesh, camera, rot, trans,
                                   full_window(camera, batch, frames, dtype=rot.dtype, device=rot.device),
                                   size=(camera.height, camera.width), sigma=None)
    return cover.cpu().numpy() > 0.5


def iou(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(..., T) intersection over union of bool masks (..., T, H, W); NaN where both are empty."""
    inter = (pred & true).sum((-2, -1))
    union = (pred | true).sum((-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), np.nan)


def rotation_error_deg(true_rot: np.ndarray, rot: Tensor | np.ndarray, symmetries: np.ndarray) -> np.ndarray:
    """(..., T) angle between true (T, 3, 3) and fitted (..., T, 3, 3) rotations, modulo the
    shape's symmetry group (K, 3, 3) (the smallest over ``rot @ S``), degrees."""
    rot = torch.as_tensor(np.asarray(rot.detach().cpu() if torch.is_tensor(rot) else rot), dtype=torch.float64)
    sym = torch.as_tensor(symmetries, dtype=torch.float64)
    angles = rotation_angle(torch.as_tensor(true_rot)[..., None, :, :], rot[..., None, :, :] @ sym)
    return np.degrees(angles.amin(-1).numpy())


def full_loss(problem: Problem, cands: Candidates, crop: int = 64, sigma: float = 0.5) -> Tensor:
    """(B,) the search's silhouette loss over all frames at one fixed crop and edge width, so
    that losses from different stages compare."""
    with torch.no_grad():
        return candidate_losses(problem, cands, len(problem.times), crop, sigma)


def box(mask: np.ndarray) -> list[float]:
    """``(x0, y0, x1, y1)`` of a bool mask, NaN when empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [math.nan] * 4
    return [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())]
