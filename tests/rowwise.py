"""The exact picture of a rolling-shutter camera, the reference the first-order shutter is tested
against (tests/test_render.py, tests/test_discover_video.py)."""

import torch

from torchfit.dynamics import simulate
from torchfit.render import full_window, render_silhouettes


def row_by_row(mesh, camera, state, body, gravity, frame_times, line_delay, *, start=None, sigma=None):
    """(T, H, W) silhouettes of a rolling-shutter camera, each row rendered from its own pose.

    Row ``y`` of frame ``k`` is drawn from the flight at ``frame_times[k] + line_delay (y - cy)``.
    The flight (state (1, 13) at time ``start``, default ``frame_times[0]``; integrated with
    1 ms RK4 steps) does not exist before ``start``: rows exposed earlier are drawn at ``start``,
    so a frame whose first rows fall before it is not exact. ``sigma``: the render's edge width
    (None: hard masks).
    """
    frame_times = torch.as_tensor(frame_times, dtype=state.dtype)
    start = float(frame_times[0]) if start is None else start
    height = camera.height
    rows = torch.arange(height, dtype=state.dtype)
    every = (frame_times[:, None] + line_delay * (rows - camera.cy)).reshape(-1).clamp(min=start)
    unique, index = torch.unique(torch.cat((every.new_tensor([start]), every)), sorted=True, return_inverse=True)
    traj = simulate(state, unique, body, gravity, step_size=1e-3)
    rot = traj.rot[:, index[1:]].unflatten(1, (len(frame_times), height))
    position = traj.position[:, index[1:]].unflatten(1, (len(frame_times), height))
    window = full_window(camera, 1, height, dtype=state.dtype)
    out = []
    for k in range(len(frame_times)):
        each = render_silhouettes(mesh, camera, rot[:, k], position[:, k], window, size=(height, camera.width),
                                  sigma=sigma)[0]  # (rows, H, W): image y drawn at row y's time
        out.append(each[torch.arange(height), torch.arange(height)])
    return torch.stack(out)
