"""The search's fit against the truth, before and after discover's exact-moment refinement.

    python experiments/discover/polish_check.py SET:NAME:MASKS...   # ~25 s each
    # SET: ship (torchfit/recordings) or 0, 1, 2 (the concealed sets); MASKS: seg or true

For each recording: the search from no guess (`torchfit.search.fit`, its pixel polish at crop 64,
edge 0.5 crop px), then discover's baseline refinement from it (Levenberg-Marquardt on the exact
silhouette moments with the edge nuisance, ``VideoProblem.fit(())``, edge term 0.1 px on the
segmentation and 0.01 px on true masks). Printed: each one's error at the first fitted frame
against truth.json: rotation (degrees, modulo the shape's symmetries), position (mm), its depth
part (% of depth), its lateral part (mm) and the gravity direction (degrees).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import torch
from make_concealed import fresh_folder
from true_masks import load_problem, recording_parts

import torchfit.discover_video as dv
from torchfit.discover_video import VideoProblem
from torchfit.rotation import quat_to_matrix, rotation_angle
from torchfit.search import SearchSettings, fit



def errors(state, grav, truth, frame, shape) -> dict:
    """Errors of a (13,) state and (3,) gravity against truth.json's frame ``frame``."""
    pf = truth["per_frame"]
    R = torch.tensor(pf["R"][frame], dtype=torch.float64); p = torch.tensor(pf["position"][frame], dtype=torch.float64)
    sym = torch.as_tensor(shape.symmetries, dtype=torch.float64)
    rot = quat_to_matrix(state[3:7])
    gdir = torch.tensor(truth["gravity_dir"], dtype=torch.float64)
    d = state[0:3] - p
    return dict(rot=math.degrees(float(rotation_angle(R, rot @ sym).min())), pos_mm=1000*float(d.norm()),
                depth_pct=100*float(d[2]/p[2]), lat_mm=1000*float(d[:2].norm()),
                grav=math.degrees(float(torch.acos((grav / grav.norm() @ gdir).clamp(-1, 1)))))


for arg in sys.argv[1:]:
    fresh, name, kind = arg.split(":")
    folder = (Path(__file__).resolve().parents[2] / "torchfit" / "recordings" if fresh == "ship"
              else fresh_folder(int(fresh))) / name
    truth, shape, camera = recording_parts(folder)
    obs, problem, span = load_problem(folder, shape, camera, kind == "true")
    frame = int(span[0])
    t0 = time.perf_counter()
    result = fit(problem, SearchSettings(), progress=None)
    st = result.state[0].detach().double(); gr = result.candidates.gravity(problem.g)[0].detach().double()
    e_search = errors(st, gr, truth, frame, shape)
    edge = 0.1 if kind == "seg" else 0.01
    video = VideoProblem(problem, candidates=(), edge_px=edge)
    # VideoProblem.fit runs the search itself: hand it this one
    orig = dv.fit
    dv.fit = lambda *a, **k: result
    try:
        mf = video.fit((), None)
    finally:
        dv.fit = orig
    model = mf.payload["model"]
    c = model.cands
    st2 = c.state(video.problem.body)[0].double()
    gr2 = c.gravity(problem.g)[0].double()
    e_lm = errors(st2, gr2, truth, frame, shape)
    print(f"{fresh}:{name}:{kind} search " + " ".join(f"{k}={v:.3f}" for k, v in e_search.items())
          + " | LM " + " ".join(f"{k}={v:.3f}" for k, v in e_lm.items()) + f" edge {model.edge[0]:+.3f} ({time.perf_counter()-t0:.0f}s)", flush=True)
