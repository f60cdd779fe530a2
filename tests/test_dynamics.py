import numpy as np
import pytest
import torch

from torchfit.dynamics import RigidBody, integrate, simulate
from torchfit.effects import EFFECTS, Magnus, QuadraticDrag, make_effect
from torchfit.rotation import axis_angle_to_quat
from torchfit.shape import load_shape

F64 = torch.float64


@pytest.fixture(scope="module")
def tshape():
    return load_shape(primitive="tshape", density=600.0)


def _state(batch, omega, quat=None, position=(0.0, 0.0, 2.0), velocity=(0.0, 0.0, 0.0)):
    state = torch.zeros(batch, 13, dtype=F64)
    state[:, 0:3] = torch.tensor(position, dtype=F64)
    state[:, 3:7] = torch.tensor([1.0, 0, 0, 0], dtype=F64) if quat is None else quat
    state[:, 7:10] = torch.tensor(velocity, dtype=F64)
    state[:, 10:13] = omega
    return state


def _momentum_energy(traj, body):
    rot = traj.rot
    inertia_world = rot @ body.inertia @ rot.transpose(-1, -2)
    momentum = (inertia_world @ traj.angular_velocity.unsqueeze(-1)).squeeze(-1)
    return momentum, 0.5 * (momentum * traj.angular_velocity).sum(-1)


def test_torque_free_body_conserves_energy_and_angular_momentum(tshape):
    body = RigidBody.from_shape(tshape, F64)
    torch.manual_seed(0)
    omega = torch.randn(4, 3, dtype=F64) * 4
    quat = axis_angle_to_quat(torch.randn(4, 3, dtype=F64))
    times = torch.linspace(0, 10, 101, dtype=F64)
    traj = simulate(_state(4, omega, quat), times, body, torch.zeros(3, dtype=F64), step_size=0.005)
    momentum, energy = _momentum_energy(traj, body)
    # angular momentum about the centre of mass, in the world frame, is constant
    assert ((energy - energy[:, :1]).abs() / energy[:, :1]).max() < 1e-6
    assert ((momentum - momentum[:, :1]).norm(dim=-1) / momentum[:, :1].norm(dim=-1)).max() < 1e-6


def test_intermediate_axis_flips_and_major_axis_does_not(tshape):
    body = RigidBody.from_shape(tshape, F64)
    axes = torch.as_tensor(tshape.principal_axes, dtype=F64)  # columns: minor, intermediate, major
    omega = torch.stack([6 * axes[:, i] + 0.02 * axes[:, (i + 1) % 3] for i in range(3)])
    times = torch.linspace(0, 10, 201, dtype=F64)
    traj = simulate(_state(3, omega), times, body, torch.zeros(3, dtype=F64), step_size=0.005)
    omega_body = (traj.rot.transpose(-1, -2) @ traj.angular_velocity.unsqueeze(-1)).squeeze(-1)
    along = torch.stack([omega_body[i] @ axes[:, i] for i in range(3)])  # (3, T)
    assert along[0].min() > 5.9  # minor axis: stable
    assert along[2].min() > 5.9  # major axis: stable
    assert along[1].min() < -5.0  # intermediate axis: flips (Dzhanibekov)


def test_free_fall_is_the_closed_form_parabola(tshape):
    body = RigidBody.from_shape(tshape, F64)
    gravity = 9.81 * torch.tensor([0.1, 0.9, 0.3], dtype=F64) / torch.tensor([0.1, 0.9, 0.3], dtype=F64).norm()
    p0, v0 = torch.tensor([0.1, -0.2, 2.0], dtype=F64), torch.tensor([0.5, -3.0, 0.2], dtype=F64)
    times = torch.linspace(0, 0.8, 25, dtype=F64)
    state = _state(1, torch.zeros(3, dtype=F64), position=p0.tolist(), velocity=v0.tolist())
    traj = simulate(state, times, body, gravity)
    expected = p0 + v0 * times[:, None] + 0.5 * gravity * times[:, None] ** 2
    torch.testing.assert_close(traj.position[0], expected, rtol=0, atol=1e-12)
    # spinning: the centre of mass still follows the parabola, the mesh origin does not
    state[:, 10:13] = torch.tensor([3.0, -7.0, 5.0], dtype=F64)
    traj = simulate(state, times, body, gravity)
    com = traj.position + (traj.rot @ body.com)
    com0 = com[0, 0]
    v_com0 = traj.velocity[0, 0] + torch.cross(traj.angular_velocity[0, 0], traj.rot[0, 0] @ body.com, dim=0)
    torch.testing.assert_close(com[0], com0 + v_com0 * times[:, None] + 0.5 * gravity * times[:, None] ** 2,
                               rtol=0, atol=1e-10)
    assert (traj.position[0] - expected).norm(dim=-1).max() > 1e-3


def test_outputs_shapes_and_unit_quaternions(tshape):
    body = RigidBody.from_shape(tshape)
    times = torch.linspace(0, 0.5, 16)
    state = _state(5, torch.randn(5, 3, dtype=F64) * 10).float()
    traj = simulate(state, times, body, torch.tensor([0.0, 9.81, 0.0]))
    assert traj.poses.shape == (5, 16, 7) and traj.states.shape == (5, 16, 13)
    assert traj.rot.shape == (5, 16, 3, 3)
    torch.testing.assert_close(traj.quat.norm(dim=-1), torch.ones(5, 16))
    torch.testing.assert_close(traj.states[:, 0], state, atol=1e-6, rtol=1e-6)


def test_adaptive_method_agrees_with_rk4(tshape):
    body = RigidBody.from_shape(tshape, F64)
    state = _state(2, torch.tensor([[3.0, 8.0, -2.0], [0.5, 0.1, 12.0]], dtype=F64))
    times = torch.linspace(0, 1, 31, dtype=F64)
    gravity = torch.tensor([0.0, 9.81, 0.0], dtype=F64)
    fixed = simulate(state, times, body, gravity, step_size=1e-3)
    adaptive = simulate(state, times, body, gravity, method="dopri5", rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(fixed.states, adaptive.states, atol=1e-8, rtol=1e-8)


def test_drag_slows_and_magnus_deflects(tshape):
    body = RigidBody.from_shape(tshape, F64)
    times = torch.linspace(0, 0.5, 11, dtype=F64)
    state = _state(1, torch.tensor([0.0, 0.0, 30.0], dtype=F64), velocity=(5.0, 0.0, 0.0))
    zero = torch.zeros(3, dtype=F64)
    free = simulate(state, times, body, zero)
    drag = make_effect("quadratic_drag", area=tshape.reference_area, drag_coefficient=1.0).double()
    dragged = simulate(state, times, body, zero, [drag])
    assert dragged.position[0, -1, 0] < free.position[0, -1, 0]
    lift = make_effect("magnus", area=tshape.reference_area, lift_coefficient=1.0).double()
    lifted = simulate(state, times, body, zero, [lift])
    # ω × v = (0, 0, 30) × (5, 0, 0) = (0, 150, 0): pushed toward +y
    assert lifted.position[0, -1, 1] - free.position[0, -1, 1] > 1e-4


def test_effect_forces_match_their_equations():
    from torchfit.effects import FlightState

    v = torch.tensor([[3.0, -4.0, 0.0]], dtype=F64)
    w = torch.tensor([[0.0, 0.0, 10.0]], dtype=F64)
    state = FlightState(torch.tensor(0.0), torch.zeros(1, 3), torch.eye(3)[None], v, w, torch.tensor(1.0))
    drag = QuadraticDrag(0.5, area=0.01, air_density=1.2).double()
    force, torque = drag(state)
    torch.testing.assert_close(force, -0.5 * 1.2 * 0.5 * 0.01 * 5.0 * v)
    assert torque.abs().max() == 0
    lift = Magnus(torch.tensor([0.8], dtype=F64), area=0.01, air_density=1.2).double()
    force, _ = lift(state)
    radius = (0.01 / np.pi) ** 0.5
    torch.testing.assert_close(force, 0.5 * 1.2 * 0.8 * 0.01 * radius * torch.cross(w, v, dim=-1))


def test_integrator_gradcheck(tshape):
    body = RigidBody.from_shape(tshape, F64)
    times = torch.linspace(0, 0.1, 4, dtype=F64)
    gravity = torch.tensor([0.0, 9.81, 0.0], dtype=F64)
    state = _state(1, torch.tensor([2.0, -3.0, 5.0], dtype=F64)).requires_grad_()

    def final_pose(s):
        return simulate(s, times, body, gravity).poses[:, -1]

    assert torch.autograd.gradcheck(final_pose, (state,))


def test_rate_runs_each_flight_on_its_own_clock(tshape):
    """``rate`` (B,) on the stated times is each flight alone on its true times ``t0 + r (t - t0)``:
    RK4 on the scaled derivative with step h is RK4 on the true one with step r h, so the two
    agree to rounding, with a drag force in the flight and a spin that turns the body."""
    body = RigidBody.from_shape(tshape, F64)
    times = torch.linspace(0.2, 0.7, 11, dtype=F64)
    gravity = torch.tensor([0.0, 9.81, 0.0], dtype=F64)
    drag = make_effect("quadratic_drag", area=tshape.reference_area, drag_coefficient=0.8).double().requires_grad_(False)
    rates = torch.tensor([1.0, 0.97, 1.04], dtype=F64)
    state = _state(3, torch.tensor([3.0, -8.0, 12.0], dtype=F64), velocity=(2.0, -3.0, 1.0))
    step = 0.005
    together = integrate(state, times, body, gravity, [drag], step_size=step, rate=rates)
    for b, rate in enumerate(rates):
        alone = integrate(state[b:b + 1], times[0] + rate * (times - times[0]), body, gravity, [drag],
                          step_size=step * float(rate))
        torch.testing.assert_close(together.states[b], alone.states[0], rtol=0, atol=1e-12)
    assert float((together.position[1] - together.position[0]).abs().max()) > 1e-3  # the clocks differ


def test_rate_gradcheck(tshape):
    body = RigidBody.from_shape(tshape, F64)
    times = torch.linspace(0, 0.1, 4, dtype=F64)
    gravity = torch.tensor([0.0, 9.81, 0.0], dtype=F64)
    state = _state(2, torch.tensor([2.0, -3.0, 5.0], dtype=F64), velocity=(1.0, 0.0, 0.0))
    rate = torch.tensor([0.98, 1.03], dtype=F64, requires_grad=True)

    def final_pose(r):
        return integrate(state, times, body, gravity, rate=r).poses[:, -1]

    assert torch.autograd.gradcheck(final_pose, (rate,))


@pytest.mark.parametrize("bad, message", [
    (torch.zeros(2, 12, dtype=F64), r"state must have shape \(B, 13\), got \(2, 12\)"),
    (_state(1, torch.zeros(3, dtype=F64), quat=torch.tensor([2.0, 0, 0, 0], dtype=F64)), "unit quaternions"),
    (_state(1, torch.zeros(3, dtype=F64), quat=torch.zeros(4, dtype=F64)), "unit quaternions"),
    (torch.full((1, 13), float("nan"), dtype=F64), "finite"),
])
def test_bad_states_raise(tshape, bad, message):
    body = RigidBody.from_shape(tshape, F64)
    with pytest.raises(ValueError, match=message):
        simulate(bad, torch.linspace(0, 1, 3, dtype=F64), body, torch.zeros(3, dtype=F64))


def test_bad_times_method_body_raise(tshape):
    body = RigidBody.from_shape(tshape, F64)
    state = _state(1, torch.zeros(3, dtype=F64))
    zero = torch.zeros(3, dtype=F64)
    with pytest.raises(ValueError, match="strictly increasing"):
        simulate(state, torch.tensor([0.0, 0.0], dtype=F64), body, zero)
    with pytest.raises(ValueError, match='Invalid method "rk5"'):
        simulate(state, torch.tensor([0.0, 1.0], dtype=F64), body, zero, method="rk5")
    with pytest.raises(ValueError, match="gravity must have shape"):
        simulate(state, torch.tensor([0.0, 1.0], dtype=F64), body, torch.zeros(2, dtype=F64))
    bad = RigidBody(torch.tensor(-1.0, dtype=F64), body.com, body.inertia)
    with pytest.raises(ValueError, match="mass must be positive"):
        simulate(state, torch.tensor([0.0, 1.0], dtype=F64), bad, zero)
    bad = RigidBody(body.mass, body.com, -body.inertia)
    with pytest.raises(ValueError, match="symmetric positive definite"):
        simulate(state, torch.tensor([0.0, 1.0], dtype=F64), bad, zero)
    with pytest.raises(ValueError, match='Invalid effect "drag"'):
        make_effect("drag", area=0.01)
    assert set(EFFECTS) >= {"quadratic_drag", "magnus"}
