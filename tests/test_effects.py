"""The effect library: shapes, gradients (float64 gradcheck), registry errors, body/clock/camera kinds."""

import math

import pytest
import torch

from torchfit.dynamics import RigidBody, simulate
from torchfit.effects import (
    EFFECTS,
    KINDS,
    FlightState,
    apply_effects,
    make_effect,
    revealed,
    split_effects,
)
from torchfit.shape import load_shape

F64 = torch.float64
AREA = math.pi * 0.02 ** 2
FORCE_PARAMS = {
    "quadratic_drag": {"drag_coefficient": 0.45},
    "linear_drag": {"damping": 0.01},
    "magnus": {"lift_coefficient": 0.7},
    "angular_drag": {"spin_damping": 1e-6},
    "wind": {"wind_velocity": [0.5, -1.0, 0.2], "drag_coefficient": 0.5},
}


def _state(batch=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.randn(*shape, dtype=F64, generator=generator)
    rot = torch.linalg.qr(rand(batch, 3, 3)).Q
    return FlightState(torch.tensor(0.1, dtype=F64), rand(batch, 3), rot, 3 * rand(batch, 3), 50 * rand(batch, 3),
                       torch.tensor(0.0027, dtype=F64))


def test_registry_holds_the_vocabulary_and_kinds():
    assert set(EFFECTS) == {"quadratic_drag", "linear_drag", "magnus", "angular_drag", "wind", "com_offset",
                            "inertia", "time_scale", "lens_distortion", "rolling_shutter"}
    for name, cls in EFFECTS.items():
        assert cls.name == name and cls.kind in KINDS
        assert set(cls.units) == set(cls.null_params), name
        assert cls.__doc__ and "=" in cls.__doc__.splitlines()[0], f"{name}: one-line equation in the docstring"


def test_bad_names_and_parameters_raise_listing_valid_ones():
    with pytest.raises(ValueError, match="Must be one of.*quadratic_drag"):
        make_effect("drag", area=AREA)
    with pytest.raises(ValueError, match="its parameters are.*drag_coefficient"):
        make_effect("quadratic_drag", area=AREA, drag=0.4)
    with pytest.raises(ValueError, match="wind_velocity must be a \\(3,\\)"):
        make_effect("wind", area=AREA, wind_velocity=[1.0, 2.0])
    with pytest.raises(ValueError, match="time_scale must be positive"):
        make_effect("time_scale", area=AREA, time_scale=-1.0)
    with pytest.raises(ValueError, match="area must be positive"):
        make_effect("magnus", area=-1.0)


@pytest.mark.parametrize("name", sorted(FORCE_PARAMS))
def test_force_shapes_and_null_parameters_vanish(name):
    state = _state()
    with torch.no_grad():
        force, torque = make_effect(name, area=AREA, **FORCE_PARAMS[name]).double()(state)
    assert force.shape == torque.shape == (3, 3)
    assert float(force.abs().sum() + torque.abs().sum()) > 0
    null = make_effect(name, area=AREA, **EFFECTS[name].null_params).double()
    with torch.no_grad():
        force, torque = null(state)
    assert float(force.abs().max() + torque.abs().max()) == 0.0


@pytest.mark.parametrize("name", sorted(FORCE_PARAMS))
def test_force_gradcheck_wrt_state_and_parameters(name):
    effect = make_effect(name, area=AREA, **FORCE_PARAMS[name]).double()
    base = _state(batch=2, seed=1)
    names = [n for n, _ in effect.named_parameters()]

    def func(position, velocity, omega, *params):
        clone = type(effect).__new__(type(effect))
        clone.__dict__ = {**effect.__dict__, "_parameters": dict(zip(names, params))}
        state = FlightState(base.time, position, base.rot, velocity, omega, base.mass)
        return clone(state)

    inputs = [base.position.clone().requires_grad_(), base.velocity.clone().requires_grad_(),
              base.angular_velocity.clone().requires_grad_()]
    inputs += [p.detach().clone().requires_grad_() for p in effect.parameters()]
    assert torch.autograd.gradcheck(func, inputs)


def test_per_candidate_parameters_broadcast():
    state = _state(batch=3)
    batched = make_effect("quadratic_drag", area=AREA, drag_coefficient=torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    with torch.no_grad():
        force, _ = batched.double()(state)
        single = make_effect("quadratic_drag", area=AREA, drag_coefficient=0.2).double()(state)[0]
        windless = make_effect("wind", area=AREA, wind_velocity=torch.zeros(3, 3, dtype=F64),
                               drag_coefficient=0.2).double()(state)[0]
    assert torch.allclose(force[1], single[1])
    assert torch.allclose(windless, single)  # no wind: plain drag


def test_float64_parameters_keep_their_digits():
    """A float64 parameter stays float64: discover's float64 refits step a clock by 1e-5 at 1.0,
    which a float32 round trip turned into 1.0014e-5 (a 1.4 % error in its Jacobian column)."""
    step = 1e-5
    clock = make_effect("time_scale", area=AREA, time_scale=torch.tensor(1.0 + step, dtype=F64))
    assert clock.time_scale.dtype == F64
    assert float(clock.time_scale.detach()) - 1.0 == pytest.approx(step, rel=1e-9)
    offset = make_effect("com_offset", area=AREA, offset=torch.tensor([1e-3, 0.0, 2e-9], dtype=F64))
    assert float(offset.offset.detach()[2]) == 2e-9
    assert make_effect("quadratic_drag", area=AREA, drag_coefficient=0.5).drag_coefficient.dtype == torch.get_default_dtype()


def test_magnus_is_the_textbook_lift_for_spin_across_the_flight():
    state = FlightState(torch.tensor(0.0), torch.zeros(1, 3), torch.eye(3)[None], torch.tensor([[5.0, 0, 0]]),
                        torch.tensor([[0.0, 0, 100.0]]), torch.tensor(0.0027))
    with torch.no_grad():
        force, _ = make_effect("magnus", area=AREA, lift_coefficient=0.8, air_density=1.2)(state)
    spin_ratio = 0.02 * 100 / 5
    expected = 0.5 * 1.2 * AREA * (0.8 * spin_ratio) * 5 ** 2  # ½ ρ A C_L,std |v|², along ω̂ × v̂ = +y
    assert torch.allclose(force, torch.tensor([[0.0, expected, 0.0]]), rtol=1e-6)


def test_body_clock_and_camera_effects():
    tshape = load_shape(primitive="tshape", density=600.0)
    body = RigidBody.from_shape(tshape, F64)
    effects = [make_effect("com_offset", area=1.0, offset=[0.01, 0.0, -0.02]).double(),
               make_effect("inertia", area=1.0, moment_scale=[1.0, 2.0, 0.5]).double(),
               make_effect("time_scale", area=1.0, time_scale=2.0).double(),
               make_effect("quadratic_drag", area=AREA, drag_coefficient=0.3).double()]
    kinds = split_effects(effects)
    assert [len(kinds[k]) for k in KINDS] == [1, 2, 1, 0]
    times = torch.linspace(0.0, 1.0, 5, dtype=F64)
    with torch.no_grad():
        new_body, true_times, forces = apply_effects(effects, body, times)
    assert torch.allclose(new_body.com, body.com + torch.tensor([0.01, 0.0, -0.02], dtype=F64))
    moments = torch.linalg.eigvalsh(body.inertia)
    assert torch.allclose(torch.linalg.eigvalsh(new_body.inertia), torch.sort(moments * torch.tensor([1.0, 2.0, 0.5],
                                                                                dtype=F64)).values)
    assert torch.allclose(true_times, times / 2) and forces == [effects[3]]
    new_body.validate()
    # the offset changes the flight of a spinning body: the mesh origin wobbles about the true centre
    state = torch.zeros(1, 13, dtype=F64)
    state[0, 3] = 1.0
    state[0, 10:13] = torch.tensor([0.0, 0.0, 20.0])
    a = simulate(state, times, body, torch.zeros(3, dtype=F64))
    b = simulate(state, times, new_body, torch.zeros(3, dtype=F64))
    assert float((a.position - b.position).abs().max()) > 1e-3
    # non-force effects add nothing to the ODE
    with torch.no_grad():
        force, torque = effects[0](_state())
    assert float(force.abs().max() + torque.abs().max()) == 0.0


def test_body_and_camera_effect_gradcheck():
    tshape = load_shape(primitive="tshape", density=600.0)
    body = RigidBody.from_shape(tshape, F64)
    inertia = make_effect("inertia", area=1.0).double()
    com = make_effect("com_offset", area=1.0).double()
    clock = make_effect("time_scale", area=1.0).double()
    lens = make_effect("lens_distortion", area=1.0).double()
    shutter = make_effect("rolling_shutter", area=1.0).double()
    times = torch.linspace(0.0, 0.5, 4, dtype=F64)
    points = torch.randn(2, 5, 2, dtype=F64, generator=torch.Generator().manual_seed(3)) * 0.3

    def call(module, pname, value, method, *args):
        clone = type(module).__new__(type(module))
        clone.__dict__ = {**module.__dict__, "_parameters": {**module._parameters, pname: value}}
        return getattr(clone, method)(*args)

    checks = [
        lambda s: call(inertia, "moment_scale", s, "apply_body", body).inertia,
        lambda s: call(com, "offset", s, "apply_body", body).com,
    ]
    for check, value in zip(checks, ([1.2, 0.9, 1.1], [0.01, 0.02, -0.01])):
        assert torch.autograd.gradcheck(check, (torch.tensor(value, dtype=F64, requires_grad=True),))
    assert torch.autograd.gradcheck(lambda s, t: call(clock, "time_scale", s, "true_times", t),
                                    (torch.tensor(1.1, dtype=F64, requires_grad=True), times.requires_grad_()))
    assert torch.autograd.gradcheck(
        lambda k1, k2, x: _distort(lens, k1, k2, x),
        (torch.tensor(-0.2, dtype=F64, requires_grad=True), torch.tensor(0.05, dtype=F64, requires_grad=True),
         points.requires_grad_()))
    rows = torch.tensor([[10.0, 240.0, 470.0]], dtype=F64)
    assert torch.autograd.gradcheck(lambda d: call(shutter, "line_delay", d, "row_delay", rows, 240.0),
                                    (torch.tensor(2e-5, dtype=F64, requires_grad=True),))
    assert torch.allclose(call(shutter, "line_delay", torch.tensor(1e-5, dtype=F64), "row_delay", rows, 240.0),
                          torch.tensor([[-2.3e-3, 0.0, 2.3e-3]], dtype=F64))


def test_per_candidate_clock_and_lens_act_on_each_candidate_as_alone():
    """A (B,) clock's rate is 1/s per candidate (true_times' slope), and a (B,) lens distorts (a
    (B,) shutter delays) the B·T candidate-major rows the renderer flattens with candidate
    ``n // T``'s coefficients."""
    from torchfit.effects import clock_rate

    scales = torch.tensor([0.98, 1.0, 1.05], dtype=F64)
    clock = make_effect("time_scale", area=1.0, time_scale=scales).double()
    times = torch.linspace(0.1, 0.5, 5, dtype=F64)
    rate = clock_rate([clock, make_effect("quadratic_drag", area=1.0).double()])
    slope = (clock.true_times(times)[:, -1] - times[0]) / (times[-1] - times[0])
    torch.testing.assert_close(rate.detach(), 1 / scales)
    torch.testing.assert_close(slope.detach(), 1 / scales)
    assert clock_rate([make_effect("magnus", area=1.0)]) is None
    k1, k2 = torch.tensor([-0.2, 0.0, 0.1], dtype=F64), torch.tensor([0.05, 0.0, -0.02], dtype=F64)
    lens = make_effect("lens_distortion", area=1.0, k1=k1, k2=k2).double()
    points = torch.randn(3 * 4, 6, 2, dtype=F64, generator=torch.Generator().manual_seed(5)) * 0.3
    with torch.no_grad():
        together = lens.distort(points)
        for b in range(3):
            alone = make_effect("lens_distortion", area=1.0, k1=k1[b], k2=k2[b]).double().distort(points[4 * b:4 * b + 4])
            torch.testing.assert_close(together[4 * b:4 * b + 4], alone, rtol=0, atol=1e-15)
    delays = torch.tensor([1e-5, 0.0, -2e-5], dtype=F64)
    shutter = make_effect("rolling_shutter", area=1.0, line_delay=delays).double()
    rows = torch.rand(3 * 4, 6, dtype=F64, generator=torch.Generator().manual_seed(6)) * 480
    with torch.no_grad():
        seconds = shutter.row_delay(rows, 240.0)
        for b in range(3):
            torch.testing.assert_close(seconds[4 * b:4 * b + 4], delays[b] * (rows[4 * b:4 * b + 4] - 240.0))


def _distort(lens, k1, k2, points):
    clone = type(lens).__new__(type(lens))
    clone.__dict__ = {**lens.__dict__, "_parameters": {"k1": k1, "k2": k2}}
    return clone.distort(points)


@pytest.mark.parametrize("names, own, hidden_seen", [
    ((), 0, 0),
    (("quadratic_drag",), 1, 0),
    (("magnus",), 1, 2),
    (("com_offset",), 3, 3),
    (("magnus", "com_offset"), 4, 3),
])
def test_reveals_counts_the_hidden_rotation_a_spheres_flight_comes_to_depend_on(names, own, hidden_seen):
    """A sphere's centre (all its silhouette shows) does not depend on its orientation and spin;
    with an effect it may. The rank of the centre's track against the effect's own parameters and
    the six hidden components (float64, central differences) is the effect's parameter count plus
    ``reveals``: Magnus lift sees the three numbers of ``C_L ω``; an offset centre of mass wobbles
    with the spin (three; the orientation only turns the offset, which its own three count). With
    both, the spin is seen once and ``C_L`` apart from it: :func:`revealed` caps the summed
    ``reveals`` (5) at the spin's three."""
    from torchfit.rotation import axis_angle_to_quat, quat_multiply, quat_to_matrix

    shape = load_shape(primitive="sphere", dims={"radius": 0.02}, density=80.0)
    assert shape.round and not load_shape(primitive="box", density=80.0).round
    body = RigidBody.from_shape(shape, F64)
    times = torch.linspace(0.0, 0.5, 16, dtype=F64)
    base = axis_angle_to_quat(torch.tensor([[0.3, -0.5, 0.2]], dtype=F64))
    defaults = {"quadratic_drag": [0.45], "magnus": [0.8], "com_offset": [0.004, -0.002, 0.003]}

    def centre(params: torch.Tensor) -> torch.Tensor:
        delta, omega, rest = params[:3], params[3:6], params[6:]
        effects, offset = [], 0
        for name in names:
            count = len(defaults[name])
            value = rest[offset:offset + count]
            offset += count
            key = next(iter(EFFECTS[name].null_params))
            effects.append(make_effect(name, area=shape.reference_area, **{key: value if count > 1 else value[0]}))
        true_body, true_times, forces = apply_effects(effects, body, times)
        quat = quat_multiply(axis_angle_to_quat(delta[None]), base)
        lever = (quat_to_matrix(quat) @ true_body.com[..., None])[..., 0]
        state = torch.cat((torch.tensor([[0.1, 0.0, 2.0]], dtype=F64) - lever, quat,
                           torch.tensor([[1.0, -3.0, 0.5]], dtype=F64) - torch.cross(omega[None], lever, dim=-1),
                           omega[None]), -1)
        gravity = torch.tensor([[0.0, 9.81, 0.0]], dtype=F64)
        return simulate(state, true_times, true_body, gravity, forces).position.reshape(-1)

    params = torch.tensor([0.0, 0.0, 0.0, 3.0, -5.0, 8.0] + sum((defaults[n] for n in names), []), dtype=F64)
    step = 1e-5 * torch.eye(len(params), dtype=F64)
    with torch.no_grad():
        jac = torch.stack([(centre(params + h) - centre(params - h)) / 2e-5 for h in step], -1)
    values = torch.linalg.svdvals(jac)
    rank = int((values > 1e-6 * max(float(values.max()), 1e-3)).sum())
    assert rank == own + hidden_seen
    assert revealed(names) == hidden_seen
