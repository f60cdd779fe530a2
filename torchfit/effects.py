"""Physics effects: small force/torque terms the rigid-body model adds to gravity.

Each effect is one ``nn.Module`` with named parameters in physical units, a docstring that states
its physics in one equation, and a ``forward(state) -> (force, torque)`` giving world-frame (camera
frame) force in newtons at the centre of mass and torque in newton-metres about it, (B, 3) each.
Parameters are tensors of shape () shared by the batch or (B,) one per candidate. The registry
``EFFECTS`` maps DESIGN.md's vocabulary names to these classes; names never change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = ["FlightState", "Effect", "QuadraticDrag", "Magnus", "EFFECTS", "make_effect"]

AIR_DENSITY = 1.2  # kg/m^3, sea level at 20 °C


@dataclass(frozen=True)
class FlightState:
    """The body's state inside the ODE right-hand side (world = camera frame, SI units).

    Attributes:
        time: () seconds.
        position: (B, 3) centre of mass.
        rot: (B, 3, 3) orientation, mesh axes to world.
        velocity: (B, 3) centre-of-mass velocity.
        angular_velocity: (B, 3) world frame, rad/s.
        mass: () or (B,) kg.
    """

    time: Tensor
    position: Tensor
    rot: Tensor
    velocity: Tensor
    angular_velocity: Tensor
    mass: Tensor


class Effect(nn.Module):
    """Base class: ``forward(state) -> (force (B, 3) N, torque (B, 3) N m)``, world frame."""

    name: str = ""

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError


def _as_param(name: str, value, *, positive: bool = False) -> nn.Parameter:
    tensor = torch.as_tensor(value, dtype=torch.get_default_dtype()).clone()
    if tensor.dim() > 1:
        raise ValueError(f"{name} must be a scalar or a (B,) tensor, got shape {tuple(tensor.shape)}")
    if not bool(torch.isfinite(tensor).all()) or (positive and bool((tensor <= 0).any())):
        kind = "positive and finite" if positive else "finite"
        raise ValueError(f"{name} must be {kind}, got {tensor.tolist()}")
    return nn.Parameter(tensor)


def _per_candidate(param: Tensor) -> Tensor:
    """() or (B,) parameter as a column that broadcasts against (B, 3)."""
    return param.unsqueeze(-1) if param.dim() == 1 else param


class QuadraticDrag(Effect):
    """Aerodynamic drag, quadratic in airspeed: ``F = -½ ρ C_d A |v| v``.

    ``v`` the centre-of-mass velocity (m/s, world frame), ``ρ`` the air density (kg/m³), ``A`` the
    reference area (m²; by default a quarter of the surface area, the mean projected area of a
    convex body, πr² for a sphere), ``C_d`` dimensionless (≈ 0.4–0.5 for a sphere). No torque.
    """

    name = "quadratic_drag"

    def __init__(self, drag_coefficient=0.5, *, area: float, air_density: float = AIR_DENSITY):
        super().__init__()
        self.drag_coefficient = _as_param("drag_coefficient", drag_coefficient)
        self.area = _positive_float("area", area)
        self.air_density = _positive_float("air_density", air_density)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        scale = 0.5 * self.air_density * self.area * _per_candidate(self.drag_coefficient)
        speed = state.velocity.norm(dim=-1, keepdim=True)
        force = -scale * speed * state.velocity
        return force, torch.zeros_like(force)


class Magnus(Effect):
    """Magnus lift of a spinning body: ``F = ½ ρ C_L A r (ω × v)``.

    ``ω`` rad/s and ``v`` m/s in the world frame, ``A`` the reference area (m²), ``r = √(A/π)`` the
    reference radius (m), ``C_L`` dimensionless (the lift coefficient per unit spin ratio
    ``rω/|v|``; ≈ 0.5–1 for a table-tennis ball). No torque.
    """

    name = "magnus"

    def __init__(self, lift_coefficient=0.6, *, area: float, air_density: float = AIR_DENSITY):
        super().__init__()
        self.lift_coefficient = _as_param("lift_coefficient", lift_coefficient)
        self.area = _positive_float("area", area)
        self.air_density = _positive_float("air_density", air_density)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        radius = math.sqrt(self.area / math.pi)
        scale = 0.5 * self.air_density * self.area * radius * _per_candidate(self.lift_coefficient)
        force = scale * torch.cross(state.angular_velocity, state.velocity, dim=-1)
        return force, torch.zeros_like(force)


def _positive_float(name: str, value) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be positive, got {value}")
    return value


EFFECTS: dict[str, type[Effect]] = {"quadratic_drag": QuadraticDrag, "magnus": Magnus}


def make_effect(name: str, *, area: float, **params) -> Effect:
    """Build an effect by its vocabulary name.

    Args:
        name: one of ``EFFECTS``.
        area: reference area of the body, m² (e.g. ``shape.reference_area``).
        **params: the effect's named parameters (scalars or (B,) tensors).

    Raises:
        ValueError: unknown name or bad parameter.
    """
    if name not in EFFECTS:
        raise ValueError(f'Invalid effect "{name}". Must be one of {sorted(EFFECTS)}')
    try:
        return EFFECTS[name](area=area, **params)
    except TypeError as err:
        raise ValueError(f"bad parameters for effect {name!r}: {err}") from None
