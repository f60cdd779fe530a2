"""The segmentation's mean edge bias on every recording with true masks: how far (pixels, along the
normal) the outline of torchfit.video's masks lies outside the true one, (area - true area) /
true perimeter, averaged over the used frames. It is what discover's edge-bias nuisance estimates
(`models[].edge_px` in discover.json) and what its prior (`EDGE_PRIOR_PX`) is set from.

    python experiments/discover/edge_bias.py      # ~1 min; writes results/edge_bias.json

`--by-normal` splits the bias by the direction of the outline: on the silhouette's long sides
(outline normal within 24 degrees of the minor axis) and at its ends (within 37 degrees of the
major axis), on the control and clock recordings of the first set and of fresh set 1
(`make_concealed.py --fresh 1`), and as ``b0 + b1 e cos(2 phi)`` (phi the normal's angle to the
major axis, e the silhouette's elongation), the form of discover's two-term edge nuisance, beside
what discover fitted there.
A single scalar bias cannot make a silhouette fatter and shorter at once; the second term can.

    python experiments/discover/edge_bias.py --by-normal   # ~3 min; writes results/edge_bias_by_normal.json
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
from make_concealed import fresh_folder

from torchfit.discover_video import EDGE_FORM, normal_axis_angle, signed_distance
from torchfit.losses import mask_moments
from torchfit.video import Observation, load_observation

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = [ROOT / "torchfit" / "recordings", ROOT / "experiments" / "discover" / "recordings"]


def outline(masks: np.ndarray) -> np.ndarray:
    """(T, H, W) bool: the pixels of (T, H, W) bool masks with a 4-neighbour outside the mask."""
    inner = masks.copy()
    inner[:, 1:-1, 1:-1] &= masks[:, :-2, 1:-1] & masks[:, 2:, 1:-1] & masks[:, 1:-1, :-2] & masks[:, 1:-1, 2:]
    return masks & ~inner


def _load(folder: Path) -> tuple[Observation, np.ndarray]:
    """The recording's segmented observation and its (T, H, W) bool true masks."""
    observation = load_observation(folder / "video.mp4", camera=folder / "camera.json")
    with np.load(folder / "masks.npz") as data:
        return observation, data["masks"].astype(bool)


def edge_bias(folder: Path) -> float:
    observation, truth = _load(folder)
    perimeter = outline(truth).sum((1, 2))
    bias = (observation.masks.sum((1, 2)) - truth.sum((1, 2))) / np.maximum(perimeter, 1)
    return float(bias[observation.used].mean())


def edge_bias_by_normal(folder: Path) -> dict:
    """Mean bias (pixels, segmented outline outside the true one when positive) over the true
    outline's pixels, by |cos| of the angle between the outline normal and the major axis:
    ``sides`` [0, 0.4), ``oblique`` [0.4, 0.8) (mostly corners), ``ends`` [0.8, 1]; and ``b0``,
    ``b1``: the least-squares fit of ``b0 + b1 e cos(2 phi)`` to the bias of those pixels (``e``
    the true mask's elongation, ``(l1 - l2) / (l1 + l2)`` of its covariance's eigenvalues), the form
    of discover's edge nuisance (its ``edge_px``: value ``b0``, ends_minus_sides ``2 b1``)."""
    observation, truth = _load(folder)
    parts: dict = {"sides": [], "oblique": [], "ends": []}
    cos2, biases = [], []
    for t in np.flatnonzero(observation.used):
        true_signed = signed_distance(truth[t])
        true_cov = mask_moments(torch.as_tensor(truth[t], dtype=torch.float64)[None])[2][0]
        cos2_phi, elongation = normal_axis_angle(torch.as_tensor(true_signed, dtype=torch.float64), true_cov)
        edge = np.abs(true_signed) < 0.6  # the pixels beside the true outline, either side
        cos2_phi = cos2_phi.numpy()[edge]
        cos = np.sqrt(np.clip(0.5 * (1 + cos2_phi), 0, 1))  # |cos phi|
        bias = signed_distance(observation.masks[t])[edge] - true_signed[edge]
        for (name, values), (lo, hi) in zip(parts.items(), [(0, 0.4), (0.4, 0.8), (0.8, 1.01)]):
            values.append(bias[(cos >= lo) & (cos < hi)])
        cos2.append(elongation * cos2_phi)
        biases.append(bias)
    cos2 = np.concatenate(cos2)
    (b0, b1), *_ = np.linalg.lstsq(np.stack([np.ones_like(cos2), cos2], -1), np.concatenate(biases), rcond=None)
    return {name: float(np.concatenate(values).mean()) for name, values in parts.items()} | {"b0": float(b0),
                                                                                            "b1": float(b1)}


def fitted_edge(base: Path, name: str) -> dict:
    """The edge nuisance discover fitted on the segmented recording (``fitted_b0``, ``fitted_b1``,
    pixels; its final model in results/concealed[_fresh<K>]/<name>/discover.json), where a run
    with today's nuisance (``EDGE_FORM``) stored it."""
    suffix = base.name.removeprefix("recordings")  # "" or "_fresh<K>"
    path = Path(__file__).resolve().parent / "results" / f"concealed{suffix}" / name / "discover.json"
    if not path.exists():
        return {}
    edge = json.loads(path.read_text())["models"][-1]["edge_px"]
    if edge.get("form") != EDGE_FORM:
        return {}
    return {"fitted_b0": edge["value"], "fitted_b1": edge["ends_minus_sides"] / 2}


def by_normal() -> dict:
    rows = {}
    for base in (fresh_folder(0), fresh_folder(1)):
        set_name = base.name
        for name in ["control_cylinder", "control_tshape", "control_box", "time_tshape", "time_box", "drag_light_ball"]:
            folder = base / name
            if not (folder / "masks.npz").exists():
                continue
            rows[f"{set_name}/{name}"] = row = edge_bias_by_normal(folder)
            row.update(fitted_edge(base, name))
            print(f"{set_name + '/' + name:36s}" + "  ".join(f"{k} {v:+.2f}" for k, v in row.items()), flush=True)
    return rows


def main() -> dict:
    rows = {}
    for base in FOLDERS:
        for folder in sorted(p for p in base.glob("*") if (p / "masks.npz").exists() and (p / "video.mp4").exists()):
            rows[folder.name] = edge_bias(folder)
            print(f"{folder.name:22s} {rows[folder.name]:+.3f} px", flush=True)
    return rows


if __name__ == "__main__":
    results = Path(__file__).resolve().parent / "results"
    if "--by-normal" in sys.argv[1:]:
        (results / "edge_bias_by_normal.json").write_text(json.dumps(by_normal(), indent=1))
    else:
        (results / "edge_bias.json").write_text(json.dumps(main(), indent=1))
