"""3D point tracks (the paper's eq. 4.3): loading, and a point-mass flight fitted to them.

A point track is a ball's (or any small object's) centre measured in 3D: ``t, x, y, z`` in seconds
and metres, in a world frame whose vertical axis is known (``up``; gravity is fixed to
``-g`` along it, not fitted: a measured world frame, e.g. a table's, is levelled). The object's
centre of mass follows

    ṗ = v,   m v̇ = m g + Σ F(p, v, ω),   I ω̇ = Σ τ(ω),

with ``F, τ`` from :mod:`torchfit.effects` (world frame; a sphere's rotation enters only through
Magnus, with ``ω`` the measured spin when given). The fit is least squares of the 3D positions,
batched over ``B`` tracks: per-track initial position and velocity, plus effect parameters either
shared by all tracks or one set per track, solved by Levenberg-Marquardt in float64 with exact
forward-mode Jacobians (:func:`fit_tracks`).

Loaders: :func:`load_points` for a ``t,x,y,z`` CSV and :func:`load_spindoe` for the SpinDOE
trajectories (Gossard et al. 2023, arXiv 2303.03879), cut at the table bounce.
"""

from __future__ import annotations

import copy
import csv
import io
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .effects import EFFECTS, FlightState, make_effect

__all__ = [
    "POINT_EFFECTS",
    "PointData",
    "PointFit",
    "PointModel",
    "PointTrack",
    "ballistic_start",
    "batch_tracks",
    "fit_tracks",
    "load_points",
    "load_spindoe",
    "retime_uniform",
    "simulate_points",
    "split_at_impacts",
    "synthesize_track",
    "trim_outliers",
    "write_points",
]

# Effects that act on a point track. com_offset and inertia change a rigid body's rotation, which
# a point's track does not see; lens_distortion and rolling_shutter belong to a camera.
POINT_EFFECTS = ("quadratic_drag", "linear_drag", "magnus", "angular_drag", "wind", "time_scale")


@dataclass(frozen=True)
class PointTrack:
    """One free flight measured in 3D.

    Attributes:
        times: (T,) seconds, strictly increasing.
        positions: (T, 3) metres, world frame.
        spin: (3,) measured angular velocity, rad/s, world frame, or ``None``.
        name: where it came from (file, trajectory and piece).
    """

    times: np.ndarray
    positions: np.ndarray
    spin: np.ndarray | None = None
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.times)


def _check_track(times: np.ndarray, positions: np.ndarray, source: str, min_points: int,
                 rows: np.ndarray | None = None) -> None:
    rows = np.arange(len(times)) + 1 if rows is None else rows
    bad = ~(np.isfinite(times) & np.isfinite(positions).all(-1))
    if bad.any():
        raise ValueError(f"{source}: row {int(rows[np.flatnonzero(bad)[0]])} has a value that is not a finite number")
    if len(times) < min_points:
        raise ValueError(f"{source}: {len(times)} points, need at least {min_points} to fit a flight")
    back = np.flatnonzero(np.diff(times) <= 0)
    if len(back):
        i = back[0] + 1
        raise ValueError(f"{source}: time must increase strictly, row {int(rows[i])} has t={times[i]:g} "
                         f"after t={times[i - 1]:g}")


def _parse_table(text: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Rows of four numbers from CSV text (comma or semicolon, optional header) and their line numbers."""
    lines = [(n + 1, line) for n, line in enumerate(text.splitlines()) if line.strip()]
    if not lines:
        raise ValueError(f"{source}: empty file, expected columns t,x,y,z")
    delimiter = ";" if ";" in lines[0][1] else ","
    values, numbers = [], []
    for k, (number, line) in enumerate(lines):
        cells = next(csv.reader([line], delimiter=delimiter))
        try:
            row = [float(c) for c in cells]
        except ValueError:
            if k == 0:  # a header line
                continue
            raise ValueError(f"{source}: row {number} is not four numbers t,x,y,z: {line.strip()!r}") from None
        if len(row) != 4:
            raise ValueError(f"{source}: row {number} has {len(row)} columns, expected 4 (t,x,y,z)")
        values.append(row)
        numbers.append(number)
    if not values:
        raise ValueError(f"{source}: no numeric rows, expected columns t,x,y,z")
    return np.asarray(values, dtype=np.float64), np.asarray(numbers)


def load_points(path: str | Path, *, spin: Sequence[float] | None = None, min_points: int = 6) -> PointTrack:
    """Read a ``t,x,y,z`` CSV (seconds, metres; comma or semicolon; a header line allowed).

    Args:
        path: the file.
        spin: measured spin (3,) rad/s, world frame, or ``None``.
        min_points: fewest rows accepted.

    Raises:
        ValueError: missing file, non-numeric or non-finite values, time not strictly increasing,
            too few rows; the message names the file and the row.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"data.points: no such file {str(path)!r}")
    table, rows = _parse_table(path.read_text(), str(path))
    _check_track(table[:, 0], table[:, 1:], str(path), min_points, rows)
    if spin is not None:
        spin = np.asarray(spin, dtype=np.float64)
        if spin.shape != (3,) or not np.isfinite(spin).all():
            raise ValueError(f"data.spin must be three finite numbers [wx, wy, wz] rad/s, got {spin.tolist()}")
    return PointTrack(table[:, 0], table[:, 1:], spin, path.name)


def retime_uniform(times: np.ndarray) -> np.ndarray:
    """Replace jittered time stamps by a uniform clock fitted to them.

    Gaps are counted in whole sample intervals (median interval, dropped samples allowed) and
    ``t = t₀ + k Δt`` is fitted by least squares, so the mean rate is the time stamps' own.

    Args:
        times: (T,) seconds.

    Returns:
        (T,) seconds.
    """
    steps = np.diff(times)
    interval = float(np.median(steps))
    counts = np.maximum(np.round(steps / interval), 1.0)
    index = np.concatenate([[0.0], np.cumsum(counts)])
    slope, offset = np.polyfit(index, times, 1)
    return offset + slope * index


def split_at_impacts(track: PointTrack, *, up: int = 2, g: float = 9.81, threshold: float = 1.5,
                     window: int = 4, min_points: int = 8) -> list[PointTrack]:
    """Cut a track where the ball hit something (the table, a net, a wall): its velocity jumps.

    At every sample the velocity is estimated from the ``window`` samples before it and from the
    ``window`` after it (straight-line fits after removing gravity); a jump of more than
    ``threshold`` m/s — far above what drag or lift change in a few samples, and above the noise
    — is an impact, placed at the largest jump of each run of samples above the threshold. That
    sample (in contact, or nearly) belongs to neither piece. Each piece gets ``meta["piece"]``
    (0 = before the first impact) and ``meta["after"]``: ``"start"``, ``"bounce"`` (the vertical
    velocity turned from down to up) or ``"impact"``. Pieces shorter than ``min_points`` are dropped.
    """
    times, positions = track.times, track.positions.copy()
    gravity = np.zeros(3)
    gravity[up] = -g
    lifted = positions - 0.5 * gravity * (times - times[0])[:, None] ** 2  # straight lines in free flight
    n = len(times)
    jump = np.zeros(n)
    before_v = np.zeros((n, 3))
    after_v = np.zeros((n, 3))
    for i in range(window, n - window):
        before = slice(i - window, i)
        after = slice(i + 1, i + 1 + window)
        vb = np.polyfit(times[before], lifted[before], 1)[0]
        va = np.polyfit(times[after], lifted[after], 1)[0]
        before_v[i], after_v[i] = vb, va
        jump[i] = np.linalg.norm(va - vb)
    above = jump > threshold
    cuts = []
    i = 0
    while i < n:
        if above[i]:
            j = i
            while j + 1 < n and above[j + 1]:
                j += 1
            k = i + int(np.argmax(jump[i:j + 1]))
            t_rel = times[k] - times[0]
            vz_before = before_v[k, up] + gravity[up] * t_rel
            vz_after = after_v[k, up] + gravity[up] * t_rel
            cuts.append((k, "bounce" if vz_before < 0 < vz_after else "impact"))
            i = j + 1
        else:
            i += 1
    bounds = [(-1, "start"), *cuts, (n, "end")]
    pieces = []
    for k in range(len(bounds) - 1):
        lo, kind = bounds[k]
        hi = bounds[k + 1][0]
        if hi - lo - 1 >= min_points:
            sl = slice(lo + 1, hi)
            pieces.append(replace(track, times=times[sl], positions=track.positions[sl],
                                  name=f"{track.name}#{k}", meta={**track.meta, "piece": k, "after": kind}))
    return pieces


def trim_outliers(track: PointTrack, *, threshold: float = 6.0, floor: float = 0.002, degree: int = 3,
                  rounds: int = 3) -> PointTrack:
    """Drop samples far off a smooth flight (a cubic per axis): ``|r| > threshold · σ̂``, with
    ``σ̂`` the residuals' robust scale (1.4826 · MAD, at least ``floor`` metres). Catches the
    catch, the racket and tracker glitches at a track's ends.
    """
    keep = np.ones(len(track), bool)
    for _ in range(rounds):
        t = track.times[keep] - track.times[keep][0]
        fit = np.stack([np.polyval(np.polyfit(t, track.positions[keep, a], degree), t) for a in range(3)], -1)
        residual = np.linalg.norm(track.positions[keep] - fit, axis=-1)
        scale = max(1.4826 * float(np.median(np.abs(residual))), floor)
        bad = residual > threshold * scale
        if not bad.any():
            break
        keep[np.flatnonzero(keep)[bad]] = False
    return replace(track, times=track.times[keep], positions=track.positions[keep],
                   meta={**track.meta, "dropped": int((~keep).sum())})


def load_spindoe(path: str | Path, *, retime: bool = True, pieces: Sequence[int] | None = (0,),
                 min_points: int = 8, limit: int | None = None) -> list[PointTrack]:
    """The SpinDOE trajectories (Gossard et al., *SpinDOE*, 2023, arXiv 2303.03879), cut at bounces.

    The zip holds ``index.csv`` (``traj_file,x_spin,y_spin,z_spin``, rad/s) and ``NNN.csv``
    (``t;x;y;z``, seconds and metres, table frame, z up, ~140 Hz).

    Args:
        path: ``trajectories.zip``.
        retime: replace the jittered time stamps by a fitted uniform clock (:func:`retime_uniform`).
        pieces: which pieces to keep (0 = before the first bounce, 1 = after it, ...; ``None``
            all). The measured spin is attached to every piece; it was measured once per
            trajectory, so after a bounce (which changes spin) it is only a starting guess.
        min_points: shortest piece kept.
        limit: read only the first ``limit`` trajectories (tests).

    Returns:
        The pieces, each with ``meta = {"trajectory", "piece", "dropped"}``.

    Raises:
        ValueError: unreadable zip, missing index, bad rows (naming the member and row).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"SpinDOE data: no such file {str(path)!r}")
    try:
        archive = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise ValueError(f"SpinDOE data: {str(path)!r} is not a zip file") from None
    with archive:
        members = {Path(name).name: name for name in archive.namelist() if not name.endswith("/")}
        if "index.csv" not in members:
            raise ValueError(f"SpinDOE data: {str(path)!r} has no index.csv")
        index = list(csv.DictReader(io.StringIO(archive.read(members["index.csv"]).decode())))
        tracks = []
        for row in index[:limit]:
            number = int(row["traj_file"])
            member = f"{number:03d}.csv"
            if member not in members:
                continue  # the index lists a few trajectories the folder does not hold
            source = f"{path.name}:{member}"
            table, rows = _parse_table(archive.read(members[member]).decode(), source)
            times = table[:, 0]
            if retime:  # repeated stamps occur (e.g. 056.csv row 50); the fitted clock separates them
                _check_track(np.maximum.accumulate(times) + 1e-9 * np.arange(len(times)), table[:, 1:],
                             source, 2, rows)
                times = retime_uniform(times)
            _check_track(times, table[:, 1:], source, 2, rows)
            spin = np.array([float(row[k]) for k in ("x_spin", "y_spin", "z_spin")])
            track = PointTrack(times, table[:, 1:], spin, member, {"trajectory": number})
            for piece in split_at_impacts(track, min_points=min_points):
                if pieces is None or piece.meta["piece"] in pieces:
                    piece = trim_outliers(piece)
                    if len(piece) >= min_points:
                        tracks.append(piece)
    return tracks


@dataclass(frozen=True)
class PointData:
    """Tracks padded into one batch.

    Attributes:
        times: (B, T) seconds from each track's first sample (padding repeats the last time).
        positions: (B, T, 3) metres.
        weights: (B, T) 1 for a sample, 0 for padding.
        spin: (B, 3) rad/s or ``None``.
        names: the tracks' names.
    """

    times: Tensor
    positions: Tensor
    weights: Tensor
    spin: Tensor | None
    names: tuple[str, ...]

    @property
    def batch(self) -> int:
        return self.times.shape[0]

    def expand(self, copies: int) -> PointData:
        """The batch repeated ``copies`` times, (copies * B, ...)."""
        spin = None if self.spin is None else self.spin.repeat(copies, 1)
        return PointData(self.times.repeat(copies, 1), self.positions.repeat(copies, 1, 1),
                         self.weights.repeat(copies, 1), spin, self.names * copies)

    def with_weights(self, weights: Tensor) -> PointData:
        return replace(self, weights=weights)

    def split(self, fraction: float) -> tuple[PointData, PointData]:
        """(first ``fraction`` of each track, the rest) as weight masks on the same batch."""
        counts = self.weights.sum(-1, keepdim=True)
        order = torch.cumsum(self.weights, -1)
        first = (order <= torch.ceil(fraction * counts)) & (self.weights > 0)
        return self.with_weights(first.to(self.weights)), self.with_weights((~first & (self.weights > 0)).to(self.weights))


def batch_tracks(tracks: Sequence[PointTrack], *, dtype=torch.float64) -> PointData:
    """Pad tracks into a :class:`PointData` (spin only if every track has one)."""
    if not tracks:
        raise ValueError("no tracks to fit")
    length = max(len(t) for t in tracks)
    times = np.zeros((len(tracks), length))
    positions = np.zeros((len(tracks), length, 3))
    weights = np.zeros((len(tracks), length))
    for b, track in enumerate(tracks):
        n = len(track)
        times[b, :n] = track.times - track.times[0]
        times[b, n:] = times[b, n - 1]
        positions[b, :n] = track.positions
        positions[b, n:] = track.positions[-1]
        weights[b, :n] = 1.0
    spin = None
    if all(t.spin is not None for t in tracks):
        spin = torch.as_tensor(np.stack([t.spin for t in tracks]), dtype=dtype)
    as_t = lambda a: torch.as_tensor(a, dtype=dtype)
    return PointData(as_t(times), as_t(positions), as_t(weights), spin, tuple(t.name for t in tracks))


class PointModel:
    """A point-mass flight with a list of effects, as a function of flat parameters.

    Parameters are a (B, K) matrix: per track ``p0`` (3), ``v0`` (3), the spin (3, only for
    ``magnus`` without a measured spin; ``C_L`` is then fixed to 1 and the spin fitted), then the
    effects' parameters in order (scalars 1 column, vectors 3). Effect columns are either shared
    by all tracks (tied in the fit) or one per track.

    Args:
        effects: names from ``POINT_EFFECTS``.
        area: reference area, m².
        mass: kg.
        moment: moment of inertia about any axis through the centre, kg m² (a sphere's).
        g: gravitational acceleration, m/s², along ``-up``.
        up: index of the vertical axis (2 for z up).
        spin_known: whether tracks carry a measured spin.
        step: integration step, seconds (RK4; positions between steps by cubic Hermite).
    """

    def __init__(self, effects: Sequence[str], *, area: float, mass: float, moment: float, g: float = 9.81,
                 up: int = 2, spin_known: bool = False, step: float = 0.005, air_density: float = 1.2):
        bad = [name for name in effects if name not in POINT_EFFECTS]
        if bad:
            raise ValueError(f"effects {bad} do not apply to a point track; must be among {list(POINT_EFFECTS)}")
        self.effects = tuple(effects)
        self.mass, self.moment, self.step = float(mass), float(moment), float(step)
        self.spin_known = bool(spin_known)
        self.fit_spin = "magnus" in self.effects and not self.spin_known
        gravity = torch.zeros(3, dtype=torch.float64)
        gravity[up] = -float(g)
        self.gravity = gravity
        self.modules = {}
        for name in self.effects:
            params = {}
            if name == "magnus" and self.fit_spin:
                params = {"lift_coefficient": 1.0}
            extra = {"air_density": air_density} if name in ("quadratic_drag", "magnus", "wind") else {}
            self.modules[name] = make_effect(name, area=area, **params, **extra).double()
        self.columns: list[tuple[str, str, int]] = [("", "p0", 3), ("", "v0", 3)]
        if self.fit_spin:
            self.columns.append(("magnus", "spin", 3))
        self.n_local = sum(size for *_, size in self.columns)
        for name in self.effects:
            if name == "magnus" and self.fit_spin:
                continue
            for pname, null in EFFECTS[name].null_params.items():
                self.columns.append((name, pname, 3 if isinstance(null, (tuple, list)) else 1))
        self.n_params = sum(size for *_, size in self.columns)

    def typical_scale(self) -> Tensor:
        """(K,) a typical magnitude per column (finite-difference steps are relative to it)."""
        scales = {"p0": 1.0, "v0": 1.0, "spin": 10.0, "damping": 1e-3, "spin_damping": 1e-7}
        return torch.tensor([scales.get(pname, 1.0) for _, pname, size in self.columns for _ in range(size)],
                            dtype=torch.float64)

    def _first_effect(self) -> int:
        return 3 if self.fit_spin else 2

    def unpack(self, params: Tensor) -> dict[tuple[str, str], Tensor]:
        """(B, K) -> {(effect, name): (B,) or (B, 3)}."""
        out, col = {}, 0
        for name, pname, size in self.columns:
            block = params[:, col:col + size]
            out[(name, pname)] = block if size == 3 else block[:, 0]
            col += size
        return out

    def pack(self, values: dict[tuple[str, str], Tensor], batch: int) -> Tensor:
        """Inverse of :meth:`unpack` (missing entries at their null values)."""
        blocks = []
        for name, pname, size in self.columns:
            if (name, pname) in values:
                value = torch.as_tensor(values[(name, pname)], dtype=torch.float64)
            elif name:
                value = torch.as_tensor(EFFECTS[name].null_params.get(pname, 0.0), dtype=torch.float64)
            else:
                value = torch.zeros(3, dtype=torch.float64)
            blocks.append(value.reshape(-1, size).expand(batch, size) if value.dim() < 2 else value)
        return torch.cat(blocks, dim=-1)

    def predict(self, params: Tensor, times: Tensor, spin: Tensor | None) -> Tensor:
        """(B, K) parameters, (B, T) stated seconds from the start -> (B, T, 3) positions."""
        values = self.unpack(params)
        if "time_scale" in self.effects:
            times = times / values[("time_scale", "time_scale")].unsqueeze(-1)
        if self.fit_spin:
            spin = values[("magnus", "spin")]
        if spin is None:
            spin = torch.zeros_like(values[("", "v0")])
        forces = []
        for name in self.effects:
            if EFFECTS[name].kind != "force":
                continue
            names = [p for (e, p) in values if e == name and p != "spin"]
            forces.append((self.modules[name], {p: values[(name, p)] for p in names}))
        return simulate_points(values[("", "p0")], values[("", "v0")], spin, times, self.gravity, forces,
                               mass=self.mass, moment=self.moment, step=self.step)


def simulate_points(p0: Tensor, v0: Tensor, spin: Tensor, times: Tensor, gravity: Tensor, forces,
                    *, mass: float, moment: float, step: float = 0.005) -> Tensor:
    """Point-mass flight by RK4 on a uniform grid, sampled at ``times`` by cubic Hermite.

    Args:
        p0, v0, spin: (B, 3) initial position (m), velocity (m/s), angular velocity (rad/s).
        times: (B, T) seconds from the start (true clock), ≥ 0.
        gravity: (3,) m/s².
        forces: ``[(effect module, {parameter: (B,) or (B, 3) tensor}), ...]`` force-kind effects.
        mass: kg.  moment: kg m².  step: seconds.

    Returns:
        (B, T, 3) positions, metres.
    """
    batch = p0.shape[0]
    span = float(times.detach().max()) if times.numel() else 0.0
    n_steps = max(math.ceil(span / step) + 1, 1)
    eye = torch.eye(3, dtype=p0.dtype).expand(batch, 3, 3)
    mass_t = torch.as_tensor(mass, dtype=p0.dtype)

    bound = []
    for module, params in forces:  # the module with these tensors as its parameters, bound once
        clone = copy.copy(module)
        clone._parameters = {**module._parameters, **params}
        bound.append(clone)

    def rhs(time, p, v, w):
        acc = gravity.to(v).expand_as(v)
        torque = torch.zeros_like(w)
        if bound:
            state = FlightState(time, p, eye, v, w, mass_t)
            for module in bound:
                force, tau = module(state)
                acc = acc + force / mass
                torque = torque + tau
        return v, acc, torque / moment

    p, v, w = p0, v0, spin
    ps, vs = [p], [v]
    for k in range(n_steps):
        t = torch.as_tensor(k * step, dtype=p0.dtype)
        k1 = rhs(t, p, v, w)
        k2 = rhs(t + step / 2, *(x + step / 2 * d for x, d in zip((p, v, w), k1)))
        k3 = rhs(t + step / 2, *(x + step / 2 * d for x, d in zip((p, v, w), k2)))
        k4 = rhs(t + step, *(x + step * d for x, d in zip((p, v, w), k3)))
        p, v, w = (x + step / 6 * (a + 2 * b + 2 * c + d) for x, a, b, c, d in zip((p, v, w), k1, k2, k3, k4))
        ps.append(p)
        vs.append(v)
    grid_p = torch.stack(ps, 1)  # (B, N + 1, 3)
    grid_v = torch.stack(vs, 1)
    where = times / step
    index = where.detach().floor().clamp(0, n_steps - 1).long()  # (B, T)
    u = (where - index).unsqueeze(-1)
    take = lambda grid, i: torch.gather(grid, 1, i.unsqueeze(-1).expand(-1, -1, 3))
    p_a, p_b = take(grid_p, index), take(grid_p, index + 1)
    v_a, v_b = take(grid_v, index) * step, take(grid_v, index + 1) * step
    u2, u3 = u * u, u * u * u
    return ((2 * u3 - 3 * u2 + 1) * p_a + (u3 - 2 * u2 + u) * v_a + (-2 * u3 + 3 * u2) * p_b + (u3 - u2) * v_b)


def ballistic_start(data: PointData, gravity: Tensor) -> Tensor:
    """(B, 6) ``p0, v0`` of the drag-free parabola fitted to each track (linear least squares)."""
    t = data.times
    design = torch.stack([torch.ones_like(t), t], -1) * data.weights.unsqueeze(-1).sqrt()  # (B, T, 2)
    target = (data.positions - 0.5 * gravity * t.unsqueeze(-1) ** 2) * data.weights.unsqueeze(-1).sqrt()
    coef = torch.linalg.lstsq(design, target).solution  # (B, 2, 3)
    return torch.cat([coef[:, 0], coef[:, 1]], -1)


@dataclass
class PointFit:
    """A fitted :class:`PointModel`.

    Attributes:
        model: the model.
        params: (B, K) fitted parameters.
        shared: whether effect columns are tied across tracks.
        rss: () sum of squared residuals over the weighted samples, m².
        n_obs: number of scalar observations (3 per weighted sample).
        n_free: number of free parameters.
        covariance: (B, K, K) per-track covariance (unit noise variance: multiply by σ²), and
            for a shared fit ``shared_covariance`` (E, E) of the effect columns.
        residual: (B, T, 3) observed - predicted on all samples, m.
        iterations: LM iterations.
    """

    model: PointModel
    params: Tensor
    shared: bool
    rss: float
    n_obs: int
    n_free: int
    covariance: Tensor
    shared_covariance: Tensor | None
    residual: Tensor
    iterations: int


def _residual(model: PointModel, params: Tensor, data: PointData) -> Tensor:
    return (data.positions - model.predict(params, data.times, data.spin)) * data.weights.unsqueeze(-1).sqrt()


@torch.no_grad()
def fit_tracks(model: PointModel, data: PointData, start: Tensor, *, shared: bool = True, iterations: int = 40,
               tol: float = 1e-7) -> PointFit:
    """Levenberg-Marquardt least squares of the 3D positions (paper eq. 4.3), float64.

    Per-track columns (``p0, v0``, spin) are free for each track; effect columns are tied across
    the batch when ``shared`` (the arrow-shaped normal equations are solved by the Schur
    complement), else free per track (block-diagonal). Jacobians are exact (forward mode).

    Args:
        model: the flight model.
        data: the tracks; samples with weight 0 do not count (hold-out).
        start: (B, K) initial parameters (tied columns: equal rows).
        shared: tie the effect columns.

    Returns:
        The :class:`PointFit`.
    """
    params = start.clone().to(torch.float64)
    batch, k = params.shape
    n_local = model.n_local if shared else k

    def residual_flat(p):
        return _residual(model, p, data).reshape(batch, -1)

    typical = model.typical_scale().to(params)

    def jacobian(p):
        # central differences, all 2K perturbed copies in one batched simulation: forward-mode
        # AD through the integrator runs ~20x slower on CPU (python decompositions)
        steps = 1e-6 * (p.abs() + typical)  # (B, K)
        shifts = torch.diag_embed(steps).transpose(0, 1)  # (K, B, K)
        stacked = torch.cat([p + shifts, p - shifts]).reshape(2 * k * batch, k)
        tiled = data.expand(2 * k)
        out = _residual(model, stacked, tiled).reshape(2, k, batch, -1)
        return ((out[0] - out[1]) / (2 * steps.T.unsqueeze(-1))).permute(1, 2, 0)  # (B, N, K)

    r = residual_flat(params)
    cost = float((r * r).sum())
    damping = torch.full((batch,), 1e-3, dtype=torch.float64) if not shared else torch.tensor([1e-3], dtype=torch.float64)
    it = 0
    for it in range(1, iterations + 1):
        jac = jacobian(params)
        normal = jac.transpose(1, 2) @ jac  # (B, K, K)
        grad = (jac.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1)  # (B, K), -½ ∇cost
        improved = False
        for _ in range(12):
            step = _solve(normal, grad, damping, n_local, shared)
            trial = params - step  # r = observed - predicted, so J = -∂prediction/∂p
            r_trial = residual_flat(trial)
            per_track = (r_trial * r_trial).sum(-1)
            old_track = (r * r).sum(-1)
            if shared:
                if bool(torch.isfinite(per_track).all()) and float(per_track.sum()) < cost:
                    params, r, improved = trial, r_trial, True
                    damping = damping * 0.3
                    break
                damping = damping * 10
            else:
                better = torch.isfinite(per_track) & (per_track < old_track)
                params = torch.where(better.unsqueeze(-1), trial, params)
                r = torch.where(better.unsqueeze(-1), r_trial, r)
                damping = torch.where(better, damping * 0.3, damping * 10)
                if bool(better.any()):
                    improved = True
                    break
        new_cost = float((r * r).sum())
        if not improved or cost - new_cost <= tol * max(cost, 1e-30):
            cost = new_cost
            break
        cost = new_cost
    jac = jacobian(params)
    normal = jac.transpose(1, 2) @ jac
    covariance = torch.linalg.pinv(normal)
    shared_cov = None
    if shared and k > n_local:
        schur = _schur(normal, n_local)
        shared_cov = torch.linalg.pinv(schur)
    n_obs = int(3 * data.weights.sum())
    n_free = batch * n_local + (k - n_local) * (1 if shared else batch)
    full = (data.positions - model.predict(params, data.times, data.spin)).detach()
    return PointFit(model, params.detach(), shared, cost, n_obs, n_free, covariance, shared_cov, full, it)


def _schur(normal: Tensor, n_local: int) -> Tensor:
    a = normal[:, :n_local, :n_local]
    c = normal[:, :n_local, n_local:]
    d = normal[:, n_local:, n_local:].sum(0)
    return d - (c.transpose(1, 2) @ torch.linalg.solve(a, c)).sum(0)


def _solve(normal: Tensor, grad: Tensor, damping: Tensor, n_local: int, shared: bool) -> Tensor:
    """LM step for the (B, K, K) normal equations; tied columns after ``n_local`` when shared."""
    diag = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
    if not shared or normal.shape[-1] == n_local:
        lam = damping if damping.numel() == normal.shape[0] else damping.expand(normal.shape[0])
        damped = normal + torch.diag_embed(lam.unsqueeze(-1) * diag)
        return (torch.linalg.pinv(damped, hermitian=True) @ grad.unsqueeze(-1)).squeeze(-1)
    lam = float(damping)
    damped = normal.clone()
    local_diag = diag[:, :n_local]
    damped[:, :n_local, :n_local] += torch.diag_embed(lam * local_diag)
    a = damped[:, :n_local, :n_local]
    c = damped[:, :n_local, n_local:]
    d = normal[:, n_local:, n_local:].sum(0)
    d = d + torch.diag(lam * torch.diagonal(d))
    g_local, g_shared = grad[:, :n_local], grad[:, n_local:].sum(0)
    a_inv_c = torch.linalg.solve(a, c)  # (B, L, E)
    a_inv_g = torch.linalg.solve(a, g_local.unsqueeze(-1)).squeeze(-1)
    schur = d - (c.transpose(1, 2) @ a_inv_c).sum(0)
    rhs = g_shared - (c.transpose(1, 2) @ a_inv_g.unsqueeze(-1)).squeeze(-1).sum(0)
    delta_shared = torch.linalg.pinv(schur, hermitian=True) @ rhs  # rank-deficient when a column has no effect
    delta_local = a_inv_g - (a_inv_c @ delta_shared)
    return torch.cat([delta_local, delta_shared.expand(normal.shape[0], -1)], -1)


def synthesize_track(effects: Sequence[str] = (), params: dict | None = None, *, position=(0.0, 0.0, 0.3),
                     velocity=(4.0, 0.5, 2.5), spin=(0.0, -60.0, 20.0), samples: int = 70, rate: float = 140.0,
                     noise: float = 0.001, radius: float = 0.02, mass: float = 0.0027, g: float = 9.81,
                     seed: int = 0) -> PointTrack:
    """A ball's flight simulated by :class:`PointModel` (z up), with Gaussian noise: for tests
    and the shipped example (``params`` maps ``(effect, parameter)`` to a value).

    Returns:
        A :class:`PointTrack` with ``spin`` set.
    """
    area = math.pi * radius ** 2
    model = PointModel(effects, area=area, mass=mass, moment=2 / 3 * mass * radius ** 2, g=g, spin_known=True)
    values = {("", "p0"): torch.tensor([position]), ("", "v0"): torch.tensor([velocity])}
    values.update({key: torch.as_tensor(value) for key, value in (params or {}).items()})
    times = torch.arange(samples, dtype=torch.float64).unsqueeze(0) / rate
    spin_t = torch.tensor([spin], dtype=torch.float64)
    with torch.no_grad():
        positions = model.predict(model.pack(values, 1), times, spin_t)[0]
    generator = torch.Generator().manual_seed(seed)
    positions = positions + noise * torch.randn(positions.shape, dtype=torch.float64, generator=generator)
    return PointTrack(times[0].numpy(), positions.numpy(), np.asarray(spin, dtype=np.float64), "synthetic")


def write_points(track: PointTrack, path: str | Path, decimals: int = 4) -> None:
    """Write ``t,x,y,z`` with a header line (the format :func:`load_points` reads)."""
    rows = ["t,x,y,z"] + [",".join(f"{v:.{decimals}f}" for v in (t, *p)) for t, p in zip(track.times, track.positions)]
    Path(path).write_text("\n".join(rows) + "\n")
