"""Rigid-body free flight: Newton + Euler equations integrated by torchdiffeq for a whole batch.

State layout, (B, 13), world (= camera) frame, SI units:

    [0:3]  position of the mesh origin, metres        (``t`` of ``X_cam = R X_obj + t``)
    [3:7]  orientation quaternion (w, x, y, z) of ``R``
    [7:10] velocity of the mesh origin, m/s
    [10:13] angular velocity, rad/s, world frame

That is the user-facing convention (DESIGN.md). Internally the ODE runs on the centre of mass,

    ẋ = v,   q̇ = ½ (0, ω) ⊗ q,   m v̇ = m g + Σ F,   ω̇ = R I⁻¹ Rᵀ (Σ τ − ω × (R I Rᵀ) ω),

with ``I`` the inertia about the centre of mass in mesh axes, which is Euler's equation written
in the world frame. Extra forces and torques come from :mod:`torchfit.effects`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor, nn
from torchdiffeq import odeint
from torchdiffeq._impl.odeint import SOLVERS

from .effects import Effect, FlightState
from .rotation import check_unit_quaternion, quat_to_matrix

__all__ = ["RigidBody", "Trajectory", "FreeFlight", "simulate", "integrate", "FIXED_STEP_METHODS"]

FIXED_STEP_METHODS = ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "implicit_adams")


@dataclass(frozen=True)
class RigidBody:
    """Mass properties as tensors.

    Attributes:
        mass: () or (B,) kg.
        com: (3,) or (B, 3) centre of mass in mesh coordinates, metres.
        inertia: (3, 3) or (B, 3, 3) inertia about the centre of mass, mesh axes, kg m^2.
    """

    mass: Tensor
    com: Tensor
    inertia: Tensor

    @staticmethod
    def from_shape(shape, dtype: torch.dtype = torch.float32, device="cpu") -> "RigidBody":
        """Mass properties of a :class:`torchfit.shape.Shape`."""
        as_tensor = lambda value: torch.as_tensor(value, dtype=dtype, device=device)  # noqa: E731
        return RigidBody(as_tensor(shape.mass), as_tensor(shape.com), as_tensor(shape.inertia))

    def validate(self) -> None:
        """Raise ``ValueError`` for a non-positive mass or an inertia that is not SPD."""
        if self.com.shape[-1:] != (3,):
            raise ValueError(f"com must have shape (3,) or (B, 3), got {tuple(self.com.shape)}")
        if self.inertia.shape[-2:] != (3, 3):
            raise ValueError(f"inertia must have shape (3, 3) or (B, 3, 3), got {tuple(self.inertia.shape)}")
        if not bool((self.mass > 0).all()):
            raise ValueError(f"mass must be positive, got {self.mass.tolist()}")
        sym = 0.5 * (self.inertia + self.inertia.transpose(-1, -2))
        if not torch.allclose(sym, self.inertia, rtol=1e-5, atol=1e-12) or not bool(
                (torch.linalg.eigvalsh(sym) > 0).all()):
            raise ValueError(f"inertia must be symmetric positive definite, got {self.inertia.tolist()}")


@dataclass(frozen=True)
class Trajectory:
    """Simulated motion at the requested times, user-facing convention.

    Attributes:
        times: (T,) seconds.
        position: (B, T, 3) mesh origin, camera frame, metres.
        quat: (B, T, 4) unit quaternions (w, x, y, z) of ``R``.
        velocity: (B, T, 3) mesh-origin velocity, m/s.
        angular_velocity: (B, T, 3) world frame, rad/s.
    """

    times: Tensor
    position: Tensor
    quat: Tensor
    velocity: Tensor
    angular_velocity: Tensor

    @property
    def rot(self) -> Tensor:
        """(B, T, 3, 3) rotation matrices ``R``."""
        return quat_to_matrix(self.quat)

    @property
    def poses(self) -> Tensor:
        """(B, T, 7) position then quaternion."""
        return torch.cat((self.position, self.quat), dim=-1)

    @property
    def states(self) -> Tensor:
        """(B, T, 13) in the layout of the module docstring."""
        return torch.cat((self.position, self.quat, self.velocity, self.angular_velocity), dim=-1)


def _quat_basis() -> tuple[Tensor, Tensor]:
    """Constant maps that turn quaternion algebra into two matrix products (few, large ops).

    ``rotation(q) = (q qᵀ).flat @ ROT`` for unit q (the homogeneous form of the rotation
    matrix), and ``½ (0, ω) ⊗ q = (q @ XI).view(4, 3) @ ω``.
    """
    rot = torch.zeros(4, 4, 9, dtype=torch.float64)
    w, x, y, z = range(4)
    entries = {  # R_ij as sums of signed products q_a q_b
        0: [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)],
        1: [(x, y, 2), (w, z, -2)], 2: [(x, z, 2), (w, y, 2)],
        3: [(x, y, 2), (w, z, 2)], 4: [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)],
        5: [(y, z, 2), (w, x, -2)], 6: [(x, z, 2), (w, y, -2)], 7: [(y, z, 2), (w, x, 2)],
        8: [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
    }
    for index, terms in entries.items():
        for a, b, sign in terms:
            rot[a, b, index] += sign
    xi = torch.zeros(4, 4, 3, dtype=torch.float64)  # xi[a, row, col]: q_a's coefficient
    for row, col, a, sign in [(0, 0, x, -1), (0, 1, y, -1), (0, 2, z, -1),
                              (1, 0, w, 1), (1, 1, z, 1), (1, 2, y, -1),
                              (2, 0, z, -1), (2, 1, w, 1), (2, 2, x, 1),
                              (3, 0, y, 1), (3, 1, x, -1), (3, 2, w, 1)]:
        xi[a, row, col] = 0.5 * sign
    return rot.reshape(16, 9), xi.reshape(4, 12)


_ROT, _XI = _quat_basis()


class FreeFlight(nn.Module):
    """ODE right-hand side on the internal centre-of-mass state (B, 13).

    Written as a handful of batched matrix products: with small batches the integrator's cost
    is the number of tensor operations, not their size.

    Args:
        body: mass properties.
        gravity: (3,) or (B, 3) gravitational acceleration, camera frame, m/s^2.
        effects: extra force/torque terms, summed.
        rate: optional () or (B,) seconds of flight per second of the integration's clock: the
            derivative is multiplied by it (a clock effect, :func:`torchfit.effects.clock_rate`).
    """

    def __init__(self, body: RigidBody, gravity: Tensor, effects: Sequence[Effect] = (),
                 rate: Tensor | None = None):
        super().__init__()
        self.body = body
        self.gravity = gravity
        self.effects = nn.ModuleList(effects)
        self.rate = None if rate is None else (rate.unsqueeze(-1) if rate.dim() == 1 else rate)
        dtype, device = body.inertia.dtype, body.inertia.device
        self.inertia_t = body.inertia.transpose(-1, -2)
        self.inertia_inv_t = torch.linalg.inv(body.inertia).transpose(-1, -2)
        self.rot_basis = _ROT.to(dtype=dtype, device=device)
        self.xi_basis = _XI.to(dtype=dtype, device=device)

    def forward(self, time: Tensor, y: Tensor) -> Tensor:
        batch = y.shape[0]
        velocity, omega = y[:, 7:10], y[:, 10:13]
        quat = y[:, 3:7]
        unit = quat / quat.norm(dim=-1, keepdim=True)
        outer = (unit.unsqueeze(-1) * unit.unsqueeze(-2)).reshape(batch, 16)
        rot = (outer @ self.rot_basis).view(batch, 3, 3)  # mesh axes -> world
        acceleration = self.gravity.expand_as(velocity)
        omega_body = (omega.unsqueeze(1) @ rot).squeeze(1)  # Rᵀ ω
        momentum_body = _matvec(omega_body, self.inertia_t)
        rhs = -torch.cross(omega_body, momentum_body, dim=-1)
        if len(self.effects):
            state = FlightState(time, y[:, 0:3], rot, velocity, omega, self.body.mass)
            mass = self.body.mass.unsqueeze(-1) if self.body.mass.dim() == 1 else self.body.mass
            torque = torch.zeros_like(omega)
            for effect in self.effects:
                force, tau = effect(state)
                acceleration = acceleration + force / mass
                torque = torque + tau
            rhs = rhs + (torque.unsqueeze(1) @ rot).squeeze(1)
        # Euler's equations in body axes: I ω̇_b = τ_b − ω_b × I ω_b, then back to the world
        domega = (rot @ _matvec(rhs, self.inertia_inv_t).unsqueeze(-1)).squeeze(-1)
        dquat = ((quat @ self.xi_basis).view(batch, 4, 3) @ omega.unsqueeze(-1)).squeeze(-1)
        derivative = torch.cat((velocity, dquat, acceleration, domega), dim=-1)
        return derivative if self.rate is None else derivative * self.rate


def _matvec(vectors: Tensor, matrix_t: Tensor) -> Tensor:
    """``M v`` for (B, 3) vectors and a shared (3, 3) or per-candidate (B, 3, 3) ``Mᵀ``."""
    if matrix_t.dim() == 2:
        return vectors @ matrix_t
    return (vectors.unsqueeze(1) @ matrix_t).squeeze(1)


def _lever(quat: Tensor, com: Tensor) -> Tensor:
    """(..., 3) ``R c``: from the mesh origin to the centre of mass, world frame."""
    return (quat_to_matrix(quat) @ com.unsqueeze(-1)).squeeze(-1)


def _subdivided_grid(step_size: float):
    """A grid holding every requested time, each interval cut into equal steps ≤ step_size."""

    def constructor(func, y0, times: Tensor) -> Tensor:
        gaps = times[1:] - times[:-1]
        counts = torch.ceil(gaps.abs() / step_size - 1e-9).clamp(min=1).long().tolist()
        pieces = [times[:1]]
        for i, count in enumerate(counts):
            fractions = torch.arange(1, count + 1, dtype=times.dtype, device=times.device) / count
            pieces.append(times[i] + fractions * gaps[i])
            pieces[-1][-1] = times[i + 1]
        return torch.cat(pieces)

    return constructor


def integrate(
    state0: Tensor,
    times: Tensor,
    body: RigidBody,
    gravity: Tensor,
    effects: Sequence[Effect] = (),
    *,
    method: str = "rk4",
    step_size: float | None = None,
    rtol: float = 1e-7,
    atol: float = 1e-9,
    rate: Tensor | None = None,
) -> Trajectory:
    """:func:`simulate` without input checks, for use inside the fit (trusts its inputs).

    The quaternion of ``state0`` need not be unit; it is normalised. ``rate``, () or (B,), runs
    each flight on its own clock: ``times`` are stated seconds and ``rate`` true seconds per stated
    second (:func:`torchfit.effects.clock_rate`), so a flight with rate ``r`` is the flight at true
    times ``times[0] + r (times - times[0])``. Velocities in the result are per true second.
    """
    quat = state0[:, 3:7] / state0[:, 3:7].norm(dim=-1, keepdim=True)
    omega = state0[:, 10:13]
    lever = _lever(quat, body.com)
    y0 = torch.cat((state0[:, 0:3] + lever, quat,
                    state0[:, 7:10] + torch.cross(omega, lever, dim=-1), omega), dim=-1)
    func = FreeFlight(body, gravity, effects, rate)
    if method in FIXED_STEP_METHODS:
        if step_size is None:
            gaps = (times[1:] - times[:-1]) if len(times) > 1 else times.new_ones(1)
            step_size = float(gaps.abs().min()) / 4
        options = {"grid_constructor": _subdivided_grid(step_size)}
    else:
        options = None
    ys = odeint(func, y0, times, method=method, rtol=rtol, atol=atol, options=options)  # (T, B, 13)
    ys = ys.transpose(0, 1)  # (B, T, 13)
    quat = ys[..., 3:7] / ys[..., 3:7].norm(dim=-1, keepdim=True)
    omega = ys[..., 10:13]
    com = body.com.unsqueeze(-2) if body.com.dim() == 2 else body.com
    lever = _lever(quat, com)
    return Trajectory(times, ys[..., 0:3] - lever, quat,
                      ys[..., 7:10] - torch.cross(omega, lever, dim=-1), omega)


def simulate(
    state0: Tensor,
    times: Tensor,
    body: RigidBody,
    gravity: Tensor,
    effects: Sequence[Effect] = (),
    *,
    method: str = "rk4",
    step_size: float | None = None,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> Trajectory:
    """Integrate a batch of initial states and return the motion at ``times``.

    All ``B`` candidates go through one ``odeint`` call. Fixed-step methods (default RK4) step
    every interval between requested times in equal sub-steps no longer than ``step_size``
    (default a quarter of the shortest interval); adaptive methods (``dopri5`` …) share one step
    size across the batch, so one stiff candidate slows all.

    Args:
        state0: (B, 13) initial states at ``times[0]``, layout in the module docstring.
        times: (T,) strictly increasing seconds.
        body: mass properties.
        gravity: (3,) or (B, 3) gravitational acceleration ``g * d``, m/s^2.
        effects: extra force/torque terms (:mod:`torchfit.effects`).
        method: a torchdiffeq solver name.
        step_size: fixed-step methods' largest step, seconds.
        rtol, atol: adaptive methods' tolerances.

    Returns:
        The :class:`Trajectory` at ``times``.

    Raises:
        ValueError: bad shapes, a quaternion that is not unit, non-finite values, bad times,
            an unknown method or bad mass properties.
    """
    if state0.dim() != 2 or state0.shape[1] != 13:
        raise ValueError(f"state must have shape (B, 13), got {tuple(state0.shape)}")
    if not bool(torch.isfinite(state0).all()):
        raise ValueError("state must be finite, got NaN or inf")
    check_unit_quaternion(state0[:, 3:7], "state[:, 3:7] (orientation)")
    if times.dim() != 1 or len(times) < 1 or not bool((times[1:] > times[:-1]).all()):
        raise ValueError(f"times must be a 1-D strictly increasing tensor, got {times.tolist()}")
    if gravity.shape not in ((3,), (state0.shape[0], 3)):
        raise ValueError(f"gravity must have shape (3,) or (B, 3) = ({state0.shape[0]}, 3), "
                         f"got {tuple(gravity.shape)}")
    if method not in SOLVERS:
        raise ValueError(f'Invalid method "{method}". Must be one of {sorted(SOLVERS)}')
    if step_size is not None and not (math.isfinite(step_size) and step_size > 0):
        raise ValueError(f"step_size must be positive seconds, got {step_size}")
    body.validate()
    return integrate(state0, times, body, gravity, effects, method=method, step_size=step_size,
                     rtol=rtol, atol=atol)
