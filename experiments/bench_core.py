"""Core benchmark: the soft rasteriser's throughput and the rigid-body integrator's cost.

Measures
  1. ``render_silhouettes`` on the T-handle, silhouettes per second, forward only and
     forward + backward (to leaf ``rot`` and ``trans``), at several crop sizes and batch sizes,
     with eager and ``torch.compile``d pixel loops side by side;
  2. ``simulate`` (RK4, default sub-steps), seconds per call, forward and forward + backward;
  3. a ball drawn as its sphere against the same ball drawn as its mesh (the concealed
     recordings' 642-vertex icosphere), side by side in one process: the exact moments in
     float64, the soft coverage forward + backward in float32, and each one's error against the
     sphere's true silhouette (the ellipse of the cone that touches it);
  4. the environment.

Prints a table and writes JSON. ``--quick`` is a seconds-long smoke run (used by the tests).

    python experiments/bench_core.py                    # full run, experiments/bench_core.json
    python experiments/bench_core.py --quick --no-compile --out /tmp/quick.json
    python experiments/bench_core.py --profile          # also: torch.profiler of one eager call
    python experiments/bench_core.py --sections ball --out experiments/bench_ball.json  # the ball alone
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from torchfit import render
from torchfit.camera import Camera, project
from torchfit.dynamics import RigidBody, simulate
from torchfit.rotation import quat_to_matrix
from torchfit.shape import load_shape

DEFAULT_OUT = Path(__file__).resolve().parent / "bench_core.json"
SECTIONS = ("render", "integrator", "ball")
CAMERA = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
DEPTH = 2.0  # metres, T-handle in front of the camera
SIGMA = 1.0  # crop pixels
CONTAMINATED = 0.25  # cores used by other processes above which a timing is flagged
FRAMES_PER_SEQUENCE = 16  # N = B * T silhouettes are laid out as (N / 16, 16); the renderer flattens them


# ---------------------------------------------------------------------------------------------
# helpers


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def _time_call(fn, device: str) -> float:
    _sync(device)
    start = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - start


def _cpu_snapshot():
    """(machine busy CPU seconds, this process's CPU seconds, wall seconds), or None off Linux."""
    try:
        with open("/proc/stat") as handle:
            fields = [float(x) for x in handle.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    tick = os.sysconf("SC_CLK_TCK")
    busy = (sum(fields) - fields[3] - (fields[4] if len(fields) > 4 else 0.0)) / tick  # minus idle, iowait
    own = sum(os.times()[:2])
    return busy, own, time.perf_counter()


def _other_cores(start, end):
    """Average CPU cores used by other processes between two snapshots (timing contamination)."""
    if start is None or end is None or end[2] <= start[2]:
        return None
    return max(0.0, ((end[0] - start[0]) - (end[1] - start[1])) / (end[2] - start[2]))


def _measure(fn, device: str, repeats: int, warmup: int, budget_s: float) -> dict:
    """Median seconds of ``fn`` over ``repeats`` calls (fewer, but at least 3 or ``repeats``,
    once the timed calls exceed ``budget_s``), after ``warmup`` calls."""
    first = [_time_call(fn, device) for _ in range(warmup)]
    times = []
    snap = _cpu_snapshot()
    for _ in range(repeats):
        times.append(_time_call(fn, device))
        if len(times) >= 3 and sum(times) > budget_s:
            break
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": len(times),
            "warmup_s": first, "other_cores": _other_cores(snap, _cpu_snapshot())}


def uniform_quaternions(n: int, gen: torch.Generator, dtype=torch.float32) -> torch.Tensor:
    """(n, 4) unit quaternions, uniform on SO(3) (normalised 4-D Gaussians)."""
    quat = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    return (quat / quat.norm(dim=-1, keepdim=True)).to(dtype)


def make_poses(n: int, size: tuple[int, int], mesh: render.RenderMesh, gen: torch.Generator,
               device: str, dtype=torch.float32):
    """Random T-handle poses about ``DEPTH`` m in front of the camera and crop windows around
    each pose's projected bounding box. Returns rot (B, T, 3, 3), trans (B, T, 3), windows
    (B, T, 3), all on ``device``."""
    frames = FRAMES_PER_SEQUENCE if n % FRAMES_PER_SEQUENCE == 0 else 1
    rot = quat_to_matrix(uniform_quaternions(n, gen, torch.float64))
    offset = torch.empty(n, 3, dtype=torch.float64).uniform_(-1.0, 1.0, generator=gen)
    trans = torch.tensor([0.0, 0.0, DEPTH], dtype=torch.float64) + offset * torch.tensor([0.3, 0.2, 0.2],
                                                                                          dtype=torch.float64)
    vertices = mesh.vertices.detach().cpu().to(torch.float64)
    points = torch.einsum("nij,vj->nvi", rot, vertices) + trans.unsqueeze(1)
    pixels, _ = project(CAMERA, points)  # (n, V, 2)
    boxes = torch.cat((pixels.amin(dim=1), pixels.amax(dim=1)), dim=-1)  # (n, 4)
    windows = render.crop_windows(boxes, size)
    shape = (n // frames, frames)
    return tuple(x.to(dtype=dtype, device=device).reshape(*shape, *x.shape[1:])
                 for x in (rot, trans, windows))


def _render_case(mesh, rot, trans, windows, size, target):
    """Closures for one case: forward only (no grad) and forward + backward to leaf rot/trans."""
    rot_leaf = rot.clone().requires_grad_(True)
    trans_leaf = trans.clone().requires_grad_(True)

    def forward():
        with torch.no_grad():
            render.render_silhouettes(mesh, CAMERA, rot, trans, windows, size=size, sigma=SIGMA)

    def forward_backward():
        rot_leaf.grad = None
        trans_leaf.grad = None
        coverage = render.render_silhouettes(mesh, CAMERA, rot_leaf, trans_leaf, windows, size=size,
                                             sigma=SIGMA)
        loss = (coverage - target).square().sum()
        loss.backward()

    return forward, forward_backward, (rot_leaf, trans_leaf)


# ---------------------------------------------------------------------------------------------
# benchmarks


def bench_render(sizes, batches, modes, device: str, repeats: int, budget_s: float, seed: int = 0,
                 log=print, max_pixels: int | None = None) -> dict:
    shape = load_shape(primitive="tshape", density=600.0)
    mesh = render.RenderMesh.from_shape(shape, torch.float32, device)
    cases, setup = {}, {}
    inputs = {}
    skipped = []
    for size in sizes:
        for n in batches:
            if max_pixels and n * size * size > max_pixels:
                skipped.append({"size": size, "n": n})
                continue
            gen = torch.Generator().manual_seed(seed + 1000 * size + n)
            rot, trans, windows = make_poses(n, (size, size), mesh, gen, device)
            with torch.no_grad():  # target: the hard silhouettes of slightly moved poses
                target = render.render_silhouettes(mesh, CAMERA, rot, trans + 0.01, windows,
                                                   size=(size, size), sigma=None)
            inputs[size, n] = rot, trans, windows, target
    compile_active = False
    for mode in modes:
        start = time.perf_counter()
        active = render.set_compile(mode == "compiled")
        setup[mode] = {"set_compile_s": time.perf_counter() - start, "active": active}
        if mode == "compiled":
            compile_active = active
            if not active:
                log("torch.compile unavailable: 'compiled' rows are eager")
        for size in sizes:
            for n in batches:
                if (size, n) not in inputs:
                    continue
                rot, trans, windows, target = inputs[size, n]
                forward, forward_backward, leaves = _render_case(mesh, rot, trans, windows, (size, size),
                                                                 target)
                # two warm-up calls: the first compiles, the second may recompile with dynamic
                # shapes (the last chunk of a batch, the number of contour edges)
                fb = _measure(forward_backward, device, repeats, 2, budget_s)
                grads_ok = all(x.grad is not None and bool(torch.isfinite(x.grad).all()) for x in leaves)
                fw = _measure(forward, device, repeats, 2, budget_s)
                case = {
                    "size": size, "n": n, "mode": mode,
                    "fwd_bwd_per_s": n / fb["median_s"], "fwd_bwd_median_s": fb["median_s"],
                    "fwd_bwd_repeats": fb["repeats"], "fwd_bwd_first_call_s": fb["warmup_s"][0],
                    "fwd_per_s": n / fw["median_s"], "fwd_median_s": fw["median_s"],
                    "fwd_repeats": fw["repeats"], "fwd_first_call_s": fw["warmup_s"][0],
                    "grads_finite": grads_ok,
                    # CPU cores that other processes used while this case was timed
                    "other_cores": max((x for x in (fb["other_cores"], fw["other_cores"]) if x is not None),
                                       default=None),
                }
                cases[mode, size, n] = case
                other = case["other_cores"]
                log(f"  render {mode:8s} {size:3d}x{size:<3d} N={n:5d}: fwd+bwd {case['fwd_bwd_per_s']:9.0f}/s"
                    f"  fwd {case['fwd_per_s']:9.0f}/s  (first call {case['fwd_bwd_first_call_s']:.2f} s"
                    + (f", other processes {other:.2f} cores)" if other is not None else ")"))
    render.set_compile(False)
    dynamo = _dynamo_counters()
    ratios = []
    if "eager" in modes and "compiled" in modes:
        for size, n in inputs:
            eager, comp = cases["eager", size, n], cases["compiled", size, n]
            ratios.append({
                "size": size, "n": n,
                "fwd_bwd_compiled_over_eager": comp["fwd_bwd_per_s"] / eager["fwd_bwd_per_s"],
                "fwd_compiled_over_eager": comp["fwd_per_s"] / eager["fwd_per_s"],
            })
    compile_overhead = None
    if "compiled" in modes:
        # one-off compilation: set_compile's probe plus, per case, the warm-up calls' excess
        # over the steady-state time
        compile_overhead = setup["compiled"]["set_compile_s"] + sum(
            max(0.0, c["fwd_bwd_first_call_s"] - c["fwd_bwd_median_s"])
            + max(0.0, c["fwd_first_call_s"] - c["fwd_median_s"])
            for (mode, _, _), c in cases.items() if mode == "compiled")
    return {
        "shape": "tshape", "parts": int(mesh.edges.shape[0]), "sigma_px": SIGMA,
        "camera": {"fx": CAMERA.fx, "fy": CAMERA.fy, "width": CAMERA.width, "height": CAMERA.height},
        "depth_m": DEPTH, "compile_active": compile_active, "setup": setup,
        "compile_overhead_s": compile_overhead,
        # graphs compiled, and whether inductor's on-disk cache served them (a warm cache makes
        # compile_overhead_s much smaller than a cold one)
        "dynamo_counters": dynamo,
        "cases": list(cases.values()), "ratios": ratios, "skipped": skipped,
    }


def _dynamo_counters() -> dict:
    try:
        from torch._dynamo.utils import counters
    except ImportError:
        return {}
    return {"unique_graphs": counters["stats"].get("unique_graphs", 0),
            "frames_ok": counters["frames"].get("ok", 0),
            "fxgraph_cache_hit": counters["inductor"].get("fxgraph_cache_hit", 0),
            "fxgraph_cache_miss": counters["inductor"].get("fxgraph_cache_miss", 0)}


def bench_integrator(candidates: int, frames: int, fps: float, device: str, repeats: int,
                     budget_s: float, seed: int = 0, max_spin: float = 20.0) -> dict:
    dtype = torch.float32
    shape = load_shape(primitive="tshape", density=600.0)
    body = RigidBody.from_shape(shape, dtype, device)
    gen = torch.Generator().manual_seed(seed)
    state = torch.zeros(candidates, 13, dtype=torch.float64)
    state[:, 0:3] = torch.tensor([0.0, 0.0, DEPTH]) + 0.2 * torch.randn(candidates, 3, generator=gen,
                                                                         dtype=torch.float64)
    state[:, 3:7] = uniform_quaternions(candidates, gen, torch.float64)
    state[:, 7:10] = torch.randn(candidates, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 2.0, 0.5])
    axis = torch.randn(candidates, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    spin = max_spin * torch.rand(candidates, 1, generator=gen, dtype=torch.float64)
    state[:, 10:13] = axis * spin
    state = state.to(dtype=dtype, device=device)
    times = torch.arange(frames, dtype=dtype, device=device) / fps
    gravity = torch.tensor([0.0, 9.81, 0.0], dtype=dtype, device=device)
    leaf = state.clone().requires_grad_(True)

    def forward():
        with torch.no_grad():
            simulate(state, times, body, gravity, method="rk4")

    def forward_backward():
        leaf.grad = None
        traj = simulate(leaf, times, body, gravity, method="rk4")
        traj.position[:, -1].sum().backward()

    fw = _measure(forward, device, repeats, 1, budget_s)
    fb = _measure(forward_backward, device, repeats, 1, budget_s)
    return {
        "candidates": candidates, "frames": frames, "fps": fps, "method": "rk4",
        "substeps_per_frame": 4, "rk4_steps": 4 * (frames - 1), "dtype": "float32",
        "max_spin_rad_s": max_spin,
        "forward_s": fw["median_s"], "forward_repeats": fw["repeats"],
        "fwd_bwd_s": fb["median_s"], "fwd_bwd_repeats": fb["repeats"],
        "grads_finite": bool(torch.isfinite(leaf.grad).all()),
        "other_cores": max((x for x in (fb["other_cores"], fw["other_cores"]) if x is not None),
                           default=None),
    }


def _ellipse_moments(centres: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) area and (N, 2) centroid, pixels, of the silhouettes of spheres of ``radius`` at the
    (N, 3) camera-frame ``centres``: the ellipse ``(p · c)² = (|c|² - r²) |p|²`` on the image."""
    g = centres[:, 2] ** 2 - radius**2
    h = (centres * centres).sum(-1) - radius**2
    centre = centres[:, :2] * (centres[:, 2] / g).unsqueeze(-1)
    # semi-axes: r √h / g along the centre's direction on the image, r / √g across it
    area = torch.pi * radius**2 * h.sqrt() / g**1.5 * CAMERA.fx * CAMERA.fy
    focal = centres.new_tensor([CAMERA.fx, CAMERA.fy])
    return area, centre * focal + centres.new_tensor([CAMERA.cx, CAMERA.cy])


def bench_ball(n_moments: int, n_coverage: int, size: int, device: str, repeats: int, budget_s: float,
               seed: int = 0) -> dict:
    """A 3.3 cm ball (the concealed recordings' icosphere, 642 vertices, whose render part is
    their 256-vertex hull) 1.5-2.5 m away, drawn as its sphere (``RenderMesh.sphere``) and as its
    mesh (the same with ``sphere=None``),
    alternating: seconds of ``silhouette_moments`` (float64, ``n_moments`` poses) and of
    ``render_silhouettes`` forward + backward (float32, ``n_coverage`` poses in ``size``² crops),
    and each one's largest error against the true sphere's ellipse."""
    import dataclasses

    shape = load_shape(primitive="sphere", dims={"radius": 0.033, "subdivisions": 3}, density=380.0)
    radius = 0.033
    gen = torch.Generator().manual_seed(seed)
    count = max(n_moments, n_coverage)
    rot = quat_to_matrix(uniform_quaternions(count, gen, torch.float64))
    offset = torch.empty(count, 3, dtype=torch.float64).uniform_(-1.0, 1.0, generator=gen)
    trans = torch.tensor([0.0, 0.0, DEPTH], dtype=torch.float64) + offset * torch.tensor([0.5, 0.4, 0.5],
                                                                                          dtype=torch.float64)
    true_area, true_centre = _ellipse_moments(trans, radius)
    out = {"radius_m": radius, "mesh_vertices": len(shape.mesh.vertices),
           "hull_vertices": sum(len(part.vertices) for part in shape.parts), "moments_poses": n_moments,
           "coverage_poses": n_coverage, "crop": size}
    meshes = {}
    for dtype in (torch.float64, torch.float32):
        sphere = render.RenderMesh.from_shape(shape, dtype, device)
        meshes[dtype] = {"sphere": sphere, "mesh": dataclasses.replace(sphere, sphere=None)}
    r64, t64 = rot[:n_moments].to(device), trans[:n_moments].to(device)
    half = (true_area[:n_coverage] / torch.pi).sqrt()  # pixels, the ball's equal-area radius
    boxes = torch.cat((true_centre[:n_coverage] - half[:, None], true_centre[:n_coverage] + half[:, None]), -1)
    windows = render.crop_windows(boxes, (size, size)).to(torch.float32).unsqueeze(0).to(device)
    r32 = rot[:n_coverage].to(torch.float32).unsqueeze(0).to(device)
    t32 = trans[:n_coverage].to(torch.float32).unsqueeze(0).to(device)
    with torch.no_grad():
        target = render.render_silhouettes(meshes[torch.float32]["sphere"], CAMERA, r32, t32 + 0.002, windows,
                                           size=(size, size), sigma=None)
    timings = {name: {"moments": [], "coverage": []} for name in ("sphere", "mesh")}
    render.set_compile(False)
    for name in ("sphere", "mesh"):  # accuracy, and a warm-up of each
        with torch.no_grad():
            area, centre, _ = render.silhouette_moments(meshes[torch.float64][name], CAMERA, r64, t64)
        out[name] = {"area_error_max": float(((area.cpu() - true_area[:n_moments]) / true_area[:n_moments]).abs().max()),
                     "centroid_error_max_px": float((centre.cpu() - true_centre[:n_moments]).norm(dim=-1).max())}
    leaves = {}

    def coverage_call(name):
        rot_leaf, trans_leaf = r32.clone().requires_grad_(True), t32.clone().requires_grad_(True)
        cover = render.render_silhouettes(meshes[torch.float32][name], CAMERA, rot_leaf, trans_leaf, windows,
                                          size=(size, size), sigma=SIGMA)
        (cover - target).square().sum().backward()
        leaves[name] = bool(torch.isfinite(trans_leaf.grad).all())

    snap = _cpu_snapshot()
    spent = 0.0
    for repeat in range(repeats):
        for name in (("sphere", "mesh") if repeat % 2 == 0 else ("mesh", "sphere")):
            with torch.no_grad():
                seconds = _time_call(lambda: render.silhouette_moments(meshes[torch.float64][name], CAMERA, r64, t64),
                                     device)
            timings[name]["moments"].append(seconds)
            timings[name]["coverage"].append(_time_call(lambda: coverage_call(name), device))
            spent += seconds + timings[name]["coverage"][-1]
        if repeat >= 2 and spent > budget_s:
            break
    for name in ("sphere", "mesh"):
        out[name].update({"moments_median_s": statistics.median(timings[name]["moments"]),
                          "coverage_fwd_bwd_median_s": statistics.median(timings[name]["coverage"]),
                          "repeats": len(timings[name]["moments"]), "grads_finite": leaves[name]})
    out["moments_mesh_over_sphere"] = out["mesh"]["moments_median_s"] / out["sphere"]["moments_median_s"]
    out["coverage_mesh_over_sphere"] = (out["mesh"]["coverage_fwd_bwd_median_s"]
                                        / out["sphere"]["coverage_fwd_bwd_median_s"])
    out["other_cores"] = _other_cores(snap, _cpu_snapshot())
    return out


def environment(device: str) -> dict:
    cpu = None
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    env = {
        "torch": torch.__version__, "python": platform.python_version(), "platform": platform.platform(),
        "device": device, "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "cpu_model": cpu or platform.processor() or None,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        # other processes on the machine distort CPU timings: check this is well below the
        # number of cores
        "load_average_1min_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    if str(device).startswith("cuda"):
        env["gpu"] = torch.cuda.get_device_name(device)
    return env


def profile_render(device: str, n: int = 1024, size: int = 64, rows: int = 15) -> list[dict]:
    """torch.profiler of one eager forward + backward call; returns the top ops by self time."""
    from torch.profiler import ProfilerActivity, profile

    shape = load_shape(primitive="tshape", density=600.0)
    mesh = render.RenderMesh.from_shape(shape, torch.float32, device)
    rot, trans, windows = make_poses(n, (size, size), mesh, torch.Generator().manual_seed(7), device)
    target = torch.zeros(*rot.shape[:2], size, size, device=device)
    render.set_compile(False)
    _, forward_backward, _ = _render_case(mesh, rot, trans, windows, (size, size), target)
    forward_backward()  # warm-up
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    with profile(activities=activities) as prof:
        forward_backward()
        _sync(device)
    events = prof.key_averages()
    sort = "self_cuda_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    print(events.table(sort_by=sort, row_limit=rows))
    total = sum(e.self_cpu_time_total for e in events)
    top = sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:rows]
    return [{"op": e.key, "calls": e.count, "self_cpu_ms": e.self_cpu_time_total / 1e3,
             "self_cpu_frac": e.self_cpu_time_total / total if total else 0.0} for e in top]


# ---------------------------------------------------------------------------------------------
# report


def format_table(result: dict) -> str:
    lines = []
    if "render" in result:
        lines += _render_table(result["render"])
    if "integrator" in result:
        integ = result["integrator"]
        mark = " †" if (integ.get("other_cores") or 0.0) > CONTAMINATED else ""
        lines += ["", "| integrator | candidates | frames @ fps | RK4 steps | forward s | fwd+bwd s |",
                  "|---|---|---|---|---|---|",
                  f"| rk4 float32 | {integ['candidates']} | {integ['frames']} @ {integ['fps']:g} | "
                  f"{integ['rk4_steps']} | {integ['forward_s']:.3f}{mark} | {integ['fwd_bwd_s']:.3f}{mark} |"]
    if "ball" in result:
        ball = result["ball"]
        mark = " †" if (ball.get("other_cores") or 0.0) > CONTAMINATED else ""
        lines += ["", f"| a ball drawn as | exact moments, {ball['moments_poses']} poses, s | soft coverage "
                      f"fwd+bwd, {ball['coverage_poses']} x {ball['crop']}², s | area error, max | "
                      f"centroid error, max px |", "|---|---|---|---|---|"]
        for name, label in (("sphere", "its sphere"), ("mesh", f"its mesh ({ball['mesh_vertices']} vertices; drawn: their {ball['hull_vertices']}-vertex hull)")):
            row = ball[name]
            lines.append(f"| {label} | {row['moments_median_s']:.4f}{mark} | {row['coverage_fwd_bwd_median_s']:.4f}{mark} "
                         f"| {row['area_error_max']:.1e} | {row['centroid_error_max_px']:.1e} |")
        lines.append(f"| mesh / sphere | {ball['moments_mesh_over_sphere']:.2f} | "
                     f"{ball['coverage_mesh_over_sphere']:.2f} | | |")
    others = [c["other_cores"] for c in result.get("render", {}).get("cases", [])
              + [result[k] for k in ("integrator", "ball") if k in result] if c.get("other_cores") is not None]
    if others:
        lines += ["", f"CPU cores used by other processes while timing: at most {max(others):.2f} "
                      f"(median {statistics.median(others):.2f}); near 0 means clean timings; "
                      f"† marks cases where other processes used more than {CONTAMINATED} cores."]
    env = result["env"]
    lines += ["", f"torch {env['torch']}, device {env['device']}, {env['threads']} threads, "
                  f"CPU {env['cpu_model']}, {env['date']}"]
    return "\n".join(lines)


def _render_table(rend: dict) -> list[str]:
    lines = []
    by = {(c["mode"], c["size"], c["n"]): c for c in rend["cases"]}
    modes = [m for m in ("eager", "compiled") if any(k[0] == m for k in by)]
    sizes = sorted({c["size"] for c in rend["cases"]})
    batches = sorted({c["n"] for c in rend["cases"]})
    head = "| crop | N |" + "".join(f" {m} fwd+bwd /s | {m} fwd /s |" for m in modes)
    if len(modes) == 2:
        head += " compiled/eager fwd+bwd | compiled/eager fwd |"
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for size in sizes:
        for n in batches:
            if any((m, size, n) not in by for m in modes):
                continue
            row = f"| {size}x{size} | {n} |"
            for m in modes:
                c = by[m, size, n]
                mark = " †" if (c.get("other_cores") or 0.0) > CONTAMINATED else ""
                row += f" {c['fwd_bwd_per_s']:,.0f}{mark} | {c['fwd_per_s']:,.0f}{mark} |"
            if len(modes) == 2 and ("compiled", size, n) in by:
                e, c = by["eager", size, n], by["compiled", size, n]
                row += (f" {c['fwd_bwd_per_s'] / e['fwd_bwd_per_s']:.2f} |"
                        f" {c['fwd_per_s'] / e['fwd_per_s']:.2f} |")
            lines.append(row)
    if rend.get("skipped"):
        lines.append("")
        lines.append("Skipped (--max-pixels): " + ", ".join(f"{c['size']}x{c['size']} N={c['n']}"
                                                           for c in rend["skipped"]))
    if rend.get("compile_overhead_s") is not None:
        lines.append("")
        lines.append(f"One-off compilation (set_compile probe + warm-up excess, all cases): "
                     f"{rend['compile_overhead_s']:.1f} s; compile active: {rend['compile_active']}")
    return lines


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--quick", action="store_true", help="tiny run: 32x32, N=256, one repeat")
    parser.add_argument("--no-compile", action="store_true", help="eager kernels only")
    parser.add_argument("--sizes", type=int, nargs="+", default=None)
    parser.add_argument("--batches", type=int, nargs="+", default=None)
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per case (default 5)")
    parser.add_argument("--budget", type=float, default=30.0,
                        help="seconds per case after which repeats stop early (at least 3 are kept)")
    parser.add_argument("--candidates", type=int, default=None, help="integrator batch (default 4096)")
    parser.add_argument("--profile", action="store_true",
                        help="also profile one eager 1024 x 64x64 forward+backward call")
    parser.add_argument("--max-pixels", type=int, default=None,
                        help="skip render cases with N * H * W above this (e.g. 4096 at 128x128)")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                        help="what to measure (default: all)")
    args = parser.parse_args(argv)

    if args.threads:
        torch.set_num_threads(args.threads)
    device = args.device
    sizes = args.sizes or ([32] if args.quick else [32, 64, 128])
    batches = args.batches or ([256] if args.quick else [256, 1024, 4096])
    repeats = args.repeats or (1 if args.quick else 5)
    candidates = args.candidates or (8 if args.quick else 4096)
    modes = ["eager"] if args.no_compile else ["eager", "compiled"]

    result = {"env": environment(device),
              "config": {"quick": args.quick, "sections": args.sections, "sizes": sizes, "batches": batches,
                         "repeats": repeats,
                         "modes": modes, "argv": list(sys.argv[1:] if argv is None else argv)}}
    load = result["env"]["load_average_1min_at_start"]
    if load is not None and load > 0.5 and not device.startswith("cuda"):
        print(f"warning: 1-minute load average {load:.2f} at start; CPU timings will be distorted "
              f"by other processes", flush=True)
    if "render" in args.sections:
        print(f"render: sizes {sizes}, batches {batches}, modes {modes}, device {device}", flush=True)
        result["render"] = bench_render(sizes, batches, modes, device, repeats, args.budget,
                                        log=lambda s: print(s, flush=True), max_pixels=args.max_pixels)
    if "integrator" in args.sections:
        print(f"integrator: {candidates} candidates", flush=True)
        result["integrator"] = bench_integrator(candidates, 40, 30.0, device, repeats, args.budget)
    if "ball" in args.sections:
        print("ball: drawn as its sphere and as its mesh", flush=True)
        result["ball"] = bench_ball(200 if args.quick else 20000, 16 if args.quick else 1024, 64, device,
                                    3 if args.quick else max(repeats, 5), args.budget)
    if args.profile:
        result["profile_eager_1024x64"] = profile_render(device)
    print()
    print(format_table(result))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
