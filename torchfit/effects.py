"""Physics effects: small terms the rigid-body model adds to gravity, and the modifiers it may miss.

Each effect is one ``nn.Module`` with named parameters in physical units and a docstring that
states its physics in one equation. There are four kinds (class attribute ``kind``):

- ``"force"``: ``forward(state) -> (force, torque)``, world-frame (camera-frame) force in newtons at
  the centre of mass and torque in newton-metres about it, (B, 3) each. The ODE sums them.
- ``"body"``: ``apply_body(body) -> RigidBody``, the mass properties the flight really has
  (``com_offset``, ``inertia``).
- ``"clock"``: ``true_times(times) -> times``, the seconds that really elapsed at the stated
  sample times, and ``rate()``, true seconds per stated second (``time_scale``).
- ``"camera"``: a change to the projection (``lens_distortion``: ``distort``; ``rolling_shutter``:
  ``row_delay``).

Non-force effects return zero force and torque from ``forward``, so a list holding any mix can be
given to the ODE unchanged; :func:`split_effects` sorts a list by kind and :func:`apply_effects`
applies the body and clock ones. Parameters are tensors of shape () shared by the batch or (B,) one
per candidate (vectors: (3,) or (B, 3)). ``EFFECTS`` maps DESIGN.md's vocabulary names to the
classes; names never change. ``null_params`` on each class gives the parameter values at which the
effect vanishes (the warm start of a model-selection step), ``units`` the unit of each parameter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor, nn

__all__ = [
    "AIR_DENSITY",
    "EFFECTS",
    "KINDS",
    "AngularDrag",
    "ComOffset",
    "Effect",
    "FlightState",
    "Inertia",
    "LensDistortion",
    "LinearDrag",
    "Magnus",
    "QuadraticDrag",
    "RollingShutter",
    "TimeScale",
    "Wind",
    "apply_effects",
    "clock_rate",
    "lens_model",
    "make_effect",
    "revealed",
    "shutter_model",
    "split_effects",
]

AIR_DENSITY = 1.2  # kg/m^3, sea level at 20 °C
KINDS = ("force", "body", "clock", "camera")


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
    """Base class: ``forward(state) -> (force (B, 3) N, torque (B, 3) N m)``, world frame.

    Class attributes: ``name`` (the vocabulary name), ``kind`` (one of ``KINDS``), ``null_params``
    (parameter values at which the effect does nothing), ``units`` (parameter name -> unit),
    ``replaces`` (effects this one contains as a special case, e.g. ``wind`` contains
    ``quadratic_drag``: model selection swaps them rather than stacking them), ``bounds``
    (parameter -> (low, high) the physics allows: a fit outside says the effect is standing in for
    something else), ``reveals`` (how many of a sphere's six hidden state components, its
    orientation and spin, which no silhouette shows, the effect makes the motion depend on beyond
    what its own parameters already count: free parameters a fit on a sphere gains with it; for a
    model of several effects, :func:`revealed`).
    """

    name: str = ""
    kind: str = "force"
    null_params: ClassVar[dict] = {}
    units: ClassVar[dict] = {}
    replaces: ClassVar[tuple[str, ...]] = ()
    bounds: ClassVar[dict] = {}  # parameter -> (low, high) that the physics allows
    reveals: ClassVar[int] = 0

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        if self.kind == "force":  # pragma: no cover - abstract
            raise NotImplementedError
        zero = torch.zeros_like(state.velocity)
        return zero, zero

    def values(self) -> dict[str, Tensor]:
        """The named parameters, ``{name: tensor}`` (detached)."""
        return {key: value.detach() for key, value in self.named_parameters(recurse=False)}


def _as_param(name: str, value, *, positive: bool = False, vector: bool = False) -> nn.Parameter:
    """A floating tensor keeps its dtype (a float64 refit's parameter must not pass through float32:
    a clock step of 1e-5 at 1.0 came out as 1.0014e-5); anything else becomes the default dtype."""
    tensor = torch.as_tensor(value).clone()
    if not tensor.is_floating_point():
        tensor = tensor.to(torch.get_default_dtype())
    if vector:
        if tensor.dim() not in (1, 2) or tensor.shape[-1] != 3:
            raise ValueError(f"{name} must be a (3,) or (B, 3) vector, got shape {tuple(tensor.shape)}")
    elif tensor.dim() > 1:
        raise ValueError(f"{name} must be a scalar or a (B,) tensor, got shape {tuple(tensor.shape)}")
    if not bool(torch.isfinite(tensor).all()) or (positive and bool((tensor <= 0).any())):
        kind = "positive and finite" if positive else "finite"
        raise ValueError(f"{name} must be {kind}, got {tensor.tolist()}")
    return nn.Parameter(tensor)


def _per_candidate(param: Tensor) -> Tensor:
    """() or (B,) parameter as a column that broadcasts against (B, 3)."""
    return param.unsqueeze(-1) if param.dim() == 1 else param


def _per_row(param: Tensor, like: Tensor) -> Tensor:
    """() or (B,) parameter, cast to ``like``'s dtype, shaped to broadcast against ``like`` (N, ...)
    whose N = B·T rows are candidate-major (row ``n`` takes candidate ``n // T``'s value)."""
    param = param.to(like)
    if param.dim() == 0:
        return param
    return param.repeat_interleave(like.shape[0] // len(param)).view((-1,) + (1,) * (like.dim() - 1))


def _positive_float(name: str, value) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be positive, got {value}")
    return value


def _no_torque(force: Tensor) -> tuple[Tensor, Tensor]:
    return force, torch.zeros_like(force)


class QuadraticDrag(Effect):
    """Aerodynamic drag, quadratic in airspeed: ``F = -½ ρ C_d A |v| v``.

    ``v`` the centre-of-mass velocity (m/s, world frame), ``ρ`` the air density (kg/m³), ``A`` the
    reference area (m²; by default a quarter of the surface area, the mean projected area of a
    convex body, πr² for a sphere), ``C_d`` dimensionless (≈ 0.4–0.5 for a sphere). No torque.
    """

    name = "quadratic_drag"
    null_params: ClassVar[dict] = {"drag_coefficient": 0.0}
    units: ClassVar[dict] = {"drag_coefficient": "1"}
    bounds: ClassVar[dict] = {"drag_coefficient": (0.0, math.inf)}

    def __init__(self, drag_coefficient=0.5, *, area: float, air_density: float = AIR_DENSITY):
        super().__init__()
        self.drag_coefficient = _as_param("drag_coefficient", drag_coefficient)
        self.area = _positive_float("area", area)
        self.air_density = _positive_float("air_density", air_density)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        scale = 0.5 * self.air_density * self.area * _per_candidate(self.drag_coefficient)
        speed = state.velocity.norm(dim=-1, keepdim=True)
        return _no_torque(-scale * speed * state.velocity)


class LinearDrag(Effect):
    """Viscous (Stokes-like) drag, linear in velocity: ``F = -b v``.

    ``v`` m/s world frame, ``b`` in kg/s (Stokes: ``b = 6π μ r``, ~7e-6 kg/s for a 4 cm ball in
    air — negligible; a fitted ``b`` far above that stands in for some other velocity-dependent
    loss). No torque.
    """

    name = "linear_drag"
    null_params: ClassVar[dict] = {"damping": 0.0}
    units: ClassVar[dict] = {"damping": "kg/s"}
    bounds: ClassVar[dict] = {"damping": (0.0, math.inf)}

    def __init__(self, damping=0.0, *, area: float | None = None):
        super().__init__()
        self.damping = _as_param("damping", damping)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        return _no_torque(-_per_candidate(self.damping) * state.velocity)


class Magnus(Effect):
    """Magnus lift of a spinning body: ``F = ½ ρ C_L A r (ω × v)``.

    ``ω`` rad/s and ``v`` m/s in the world frame, ``A`` the reference area (m²), ``r = √(A/π)`` the
    reference radius (m), ``C_L`` dimensionless: the lift coefficient *per unit spin ratio*
    ``S = r|ω|/|v|``. For ω ⟂ v this is the textbook sphere lift ``½ ρ A C_L,std |v|² (ω̂ × v̂)``
    with ``C_L,std = C_L · S``; a constant ``C_L`` here means lift proportional to spin, which is
    what low-spin-ratio sphere data show (``C_L,std ≈ S`` for ``S`` ≲ 0.3, i.e. ``C_L ≈ 1``). No
    torque. On a sphere, whose spin no silhouette shows, the motion depends on the vector ``C_L ω``:
    three numbers, two more than ``C_L`` (``reveals = 2``).
    """

    name = "magnus"
    reveals = 2
    null_params: ClassVar[dict] = {"lift_coefficient": 0.0}
    units: ClassVar[dict] = {"lift_coefficient": "1 (per unit spin ratio r|w|/|v|)"}

    def __init__(self, lift_coefficient=0.6, *, area: float, air_density: float = AIR_DENSITY):
        super().__init__()
        self.lift_coefficient = _as_param("lift_coefficient", lift_coefficient)
        self.area = _positive_float("area", area)
        self.air_density = _positive_float("air_density", air_density)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        radius = math.sqrt(self.area / math.pi)
        scale = 0.5 * self.air_density * self.area * radius * _per_candidate(self.lift_coefficient)
        return _no_torque(scale * torch.cross(state.angular_velocity, state.velocity, dim=-1))


class AngularDrag(Effect):
    """Air friction on the spin: torque ``τ = -k ω``.

    ``ω`` rad/s world frame, ``k`` in N·m·s (kg m²/s). For a sphere spin then decays as
    ``exp(-k t / I)``; for a table-tennis ball (I ≈ 7.2e-7 kg m²) a decay time of a few seconds
    means k ~ 1e-7 N m s. No force.
    """

    name = "angular_drag"
    null_params: ClassVar[dict] = {"spin_damping": 0.0}
    units: ClassVar[dict] = {"spin_damping": "N m s"}
    bounds: ClassVar[dict] = {"spin_damping": (0.0, math.inf)}

    def __init__(self, spin_damping=0.0, *, area: float | None = None):
        super().__init__()
        self.spin_damping = _as_param("spin_damping", spin_damping)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        torque = -_per_candidate(self.spin_damping) * state.angular_velocity
        return torch.zeros_like(torque), torque


class Wind(Effect):
    """Quadratic drag on the air-relative velocity: ``F = -½ ρ C_d A |v - w| (v - w)``.

    ``w`` the wind (air) velocity, m/s world frame; ``C_d`` dimensionless, this effect's own. It
    contains ``quadratic_drag`` (``w = 0``), so it *replaces* that effect rather than adding a
    second drag; ``w`` and ``C_d`` are confounded on a straight, short flight (a head wind looks
    like more drag), which model selection reports through the criterion. No torque.
    """

    name = "wind"
    null_params: ClassVar[dict] = {"wind_velocity": (0.0, 0.0, 0.0), "drag_coefficient": 0.0}
    units: ClassVar[dict] = {"wind_velocity": "m/s", "drag_coefficient": "1"}
    bounds: ClassVar[dict] = {"drag_coefficient": (0.0, math.inf)}
    replaces = ("quadratic_drag",)

    def __init__(self, wind_velocity=(0.0, 0.0, 0.0), drag_coefficient=0.5, *, area: float,
                 air_density: float = AIR_DENSITY):
        super().__init__()
        self.wind_velocity = _as_param("wind_velocity", wind_velocity, vector=True)
        self.drag_coefficient = _as_param("drag_coefficient", drag_coefficient)
        self.area = _positive_float("area", area)
        self.air_density = _positive_float("air_density", air_density)

    def forward(self, state: FlightState) -> tuple[Tensor, Tensor]:
        airspeed = state.velocity - self.wind_velocity
        scale = 0.5 * self.air_density * self.area * _per_candidate(self.drag_coefficient)
        return _no_torque(-scale * airspeed.norm(dim=-1, keepdim=True) * airspeed)


class ComOffset(Effect):
    """The centre of mass is not where uniform density puts it: ``c_true = c + δ``.

    ``δ`` (m, mesh/body frame) shifts the point the body spins about; the state's mesh-origin
    position and velocity are unchanged, so the flight differs (the origin wobbles about the true
    centre of mass). The inertia about the centre is kept (the ``inertia`` effect scales it).
    Kind ``body``. On a sphere the wobble shows the spin (``reveals = 3``); the orientation only
    turns ``δ``, which its own three components already count.
    """

    name = "com_offset"
    kind = "body"
    reveals = 3
    null_params: ClassVar[dict] = {"offset": (0.0, 0.0, 0.0)}
    units: ClassVar[dict] = {"offset": "m (body frame)"}

    def __init__(self, offset=(0.0, 0.0, 0.0), *, area: float | None = None):
        super().__init__()
        self.offset = _as_param("offset", offset, vector=True)

    def apply_body(self, body):
        """The :class:`torchfit.dynamics.RigidBody` with ``com + offset`` ((3,) or (B, 3))."""
        return type(body)(body.mass, body.com + self.offset.to(body.com), body.inertia)


class Inertia(Effect):
    """The principal moments differ from uniform density's: ``I_true = V diag(s ⊙ λ) Vᵀ``.

    ``I = V diag(λ) Vᵀ`` the nominal inertia about the centre of mass (mesh axes, kg m²), ``s``
    (3,) dimensionless factors on its principal moments in ascending order of ``λ``; the principal
    axes ``V`` are kept. Kind ``body``.
    """

    name = "inertia"
    kind = "body"
    null_params: ClassVar[dict] = {"moment_scale": (1.0, 1.0, 1.0)}
    units: ClassVar[dict] = {"moment_scale": "1"}

    def __init__(self, moment_scale=(1.0, 1.0, 1.0), *, area: float | None = None):
        super().__init__()
        self.moment_scale = _as_param("moment_scale", moment_scale, positive=True, vector=True)

    def apply_body(self, body):
        """The :class:`torchfit.dynamics.RigidBody` with scaled principal moments."""
        with torch.no_grad():  # the axes are fixed: eigh's gradient is undefined for equal moments
            axes = torch.linalg.eigh(body.inertia).eigenvectors
        moments = torch.diagonal(axes.transpose(-1, -2) @ body.inertia @ axes, dim1=-2, dim2=-1)
        scaled = moments * self.moment_scale.to(moments)
        inertia = axes @ torch.diag_embed(scaled) @ axes.transpose(-1, -2)
        return type(body)(body.mass, body.com, inertia)


class TimeScale(Effect):
    """The stated frame rate is wrong: ``t_true = t_stated / s``, ``s = fps_true / fps_stated``.

    ``s`` dimensionless (1 = the stated clock is right). Seen in the trajectory as every
    acceleration scaled by ``s²`` — a look-alike of a different gravity, and along the flight of a
    changed drag. Times are measured from the first sample. Kind ``clock``.
    """

    name = "time_scale"
    kind = "clock"
    null_params: ClassVar[dict] = {"time_scale": 1.0}
    units: ClassVar[dict] = {"time_scale": "1 (true fps / stated fps)"}
    bounds: ClassVar[dict] = {"time_scale": (0.0, math.inf)}

    def __init__(self, time_scale=1.0, *, area: float | None = None):
        super().__init__()
        self.time_scale = _as_param("time_scale", time_scale, positive=True)

    def rate(self) -> Tensor:
        """() or (B,) true seconds per stated second, ``1 / s``: the ODE run on the stated clock
        is the true one with its derivative times this (:func:`clock_rate`)."""
        return 1 / self.time_scale

    def true_times(self, times: Tensor) -> Tensor:
        """(T,) or (B, T) stated seconds -> the same shape (or (B, T)) true seconds."""
        rate = self.rate().to(times)
        if rate.dim() == 1:
            rate = rate.unsqueeze(-1)
        start = times[..., :1]
        return start + (times - start) * rate


class LensDistortion(Effect):
    """Radial lens distortion the camera model leaves out: ``x_d = x (1 + k₁ r² + k₂ r⁴)``.

    ``x`` (…, 2) normalised image coordinates ``(X/Z, Y/Z)`` (camera frame, dimensionless),
    ``r = |x|``, ``k₁, k₂`` dimensionless (OpenCV's first two radial coefficients, on top of any
    the camera already has). Kind ``camera``: applied between projection and pixels.
    """

    name = "lens_distortion"
    kind = "camera"
    null_params: ClassVar[dict] = {"k1": 0.0, "k2": 0.0}
    units: ClassVar[dict] = {"k1": "1", "k2": "1"}

    def __init__(self, k1=0.0, k2=0.0, *, area: float | None = None):
        super().__init__()
        self.k1 = _as_param("k1", k1)
        self.k2 = _as_param("k2", k2)

    def distort(self, normalised: Tensor) -> Tensor:
        """(N, ..., 2) normalised coordinates -> (N, ..., 2) distorted normalised coordinates.

        With (B,) parameters, one per candidate, ``N`` is ``B`` or a multiple ``B·T`` whose rows
        are candidate-major (candidate ``b``'s T rows in a block, as the renderer flattens (B, T)
        poses): row ``n`` takes candidate ``n // T``'s parameters.
        """
        r2 = (normalised * normalised).sum(-1, keepdim=True)
        k1, k2 = _per_row(self.k1, normalised), _per_row(self.k2, normalised)
        return normalised * (1 + k1 * r2 + k2 * r2 * r2)


class RollingShutter(Effect):
    """Rows are exposed one after another: row ``y`` is seen at ``t_y = t + δ (y - c_y)``.

    ``δ`` seconds per pixel row (line delay; readout time / image height, ~10–30 µs for a CMOS
    phone camera), ``y`` the pixel row, ``c_y`` the principal point row (the frame's stated time
    is the centre row). Kind ``camera``: a point's image is drawn from the pose at its row's time
    (on video, to first order in the delay: :class:`torchfit.render.Shutter`).
    """

    name = "rolling_shutter"
    kind = "camera"
    null_params: ClassVar[dict] = {"line_delay": 0.0}
    units: ClassVar[dict] = {"line_delay": "s per pixel row"}

    def __init__(self, line_delay=0.0, *, area: float | None = None):
        super().__init__()
        self.line_delay = _as_param("line_delay", line_delay)

    def row_delay(self, rows: Tensor, cy: float) -> Tensor:
        """(N, ...) pixel rows -> (N, ...) seconds after the frame's stated time.

        With a (B,) line delay, one per candidate, ``N`` is ``B`` or a multiple ``B·T`` of
        candidate-major rows, as :meth:`LensDistortion.distort`.
        """
        return _per_row(self.line_delay, rows) * (rows - cy)


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls for cls in (QuadraticDrag, LinearDrag, Magnus, AngularDrag, Wind, ComOffset,
                              Inertia, TimeScale, LensDistortion, RollingShutter)
}


def make_effect(name: str, *, area: float, **params) -> Effect:
    """Build an effect by its vocabulary name.

    Args:
        name: one of ``EFFECTS``.
        area: reference area of the body, m² (e.g. ``shape.reference_area``); unused by effects
            that do not need it.
        **params: the effect's named parameters (scalars, (B,), (3,) or (B, 3) tensors).

    Raises:
        ValueError: unknown name or bad parameter (the message lists the valid ones).
    """
    if name not in EFFECTS:
        raise ValueError(f'Invalid effect "{name}". Must be one of {sorted(EFFECTS)}')
    cls = EFFECTS[name]
    unknown = sorted(set(params) - set(cls.null_params) - {"air_density"})
    if unknown:
        raise ValueError(f"bad parameters for effect {name!r}: {unknown}; "
                         f"its parameters are {sorted(cls.null_params)}")
    try:
        return cls(area=area, **params)
    except TypeError as err:
        raise ValueError(f"bad parameters for effect {name!r}: {err}") from None


SPIN_COMPONENTS = 3  # of a sphere's six hidden state numbers, the refits ever free only the spin


def revealed(names: Sequence[str]) -> int:
    """How many of a sphere's hidden state numbers a model with these effects sees.

    Each effect's ``reveals`` is exact alone. Together they see the spin once: Magnus lift
    (``C_L ω``, 2 beyond ``C_L``) with an offset centre of mass (the spin's 3, from the wobble)
    sees the spin's 3 and ``C_L`` apart from it, not 2 + 3 (rank of a sphere's centre track,
    tests/test_effects.py). The orientation is never seen beyond the effects' own parameters.

    Args:
        names: effect names, each in ``EFFECTS``.

    Returns:
        ``min(sum of reveals, 3)``.
    """
    return min(sum(EFFECTS[name].reveals for name in names), SPIN_COMPONENTS)


def split_effects(effects: Sequence[Effect]) -> dict[str, list[Effect]]:
    """``{kind: [effects of that kind]}`` for every kind in ``KINDS``."""
    out = {kind: [] for kind in KINDS}
    for effect in effects:
        out[effect.kind].append(effect)
    return out


def lens_model(effects: Sequence[Effect]):
    """The ``distort`` of the list's lens effect (normalised coordinates), or None."""
    return next((e.distort for e in effects if isinstance(e, LensDistortion)), None)


def clock_rate(effects: Sequence[Effect]) -> Tensor | None:
    """() or (B,) true seconds per stated second of the list's clock effects, or None without one.

    The flight on the stated clock is the true flight with the ODE's derivative times this rate
    (the forces do not depend on time), so candidates with different clocks share one time grid
    (:func:`torchfit.dynamics.integrate`'s ``rate``).
    """
    rate = None
    for effect in split_effects(effects)["clock"]:
        rate = effect.rate() if rate is None else rate * effect.rate()
    return rate


def shutter_model(effects: Sequence[Effect], cy: float):
    """The list's rolling shutter as ``rows -> seconds`` (:meth:`RollingShutter.row_delay` about
    the principal point row ``cy``), or None."""
    shutter = next((e for e in effects if isinstance(e, RollingShutter)), None)
    return None if shutter is None else (lambda rows: shutter.row_delay(rows, cy))


def apply_effects(effects: Sequence[Effect], body, times: Tensor):
    """Apply the body and clock effects of a list.

    Args:
        effects: any mix of kinds.
        body: the nominal :class:`torchfit.dynamics.RigidBody`.
        times: (T,) stated sample times, seconds.

    Returns:
        ``(body, times, forces)``: the true mass properties, the true times ((T,), or (B, T) for a
        per-candidate time scale) and the force-kind effects for the ODE.
    """
    kinds = split_effects(effects)
    for effect in kinds["body"]:
        body = effect.apply_body(body)
    for effect in kinds["clock"]:
        times = effect.true_times(times)
    return body, times, kinds["force"]
