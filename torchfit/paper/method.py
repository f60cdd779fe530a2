"""The paper's optimiser (Bhat et al., ECCV 2002, section 5), for comparison with :func:`torchfit.search.fit`.

Objective (eq. 5.1): the sum over frames of the squared difference between the simulated *hard*
(binary) silhouette and the observed one, here inside each frame's crop window around the
observed box and divided by the number of crop pixels and used frames (so it reads as the
fraction of mismatched pixels; the scale does not change the minimiser or the step, which is
normalised).

Gradient, the paper's hybrid (eq. 5.3): ``dE/dp = Σ_t dE/dq(t) · dq(t)/dp``.

* ``dq(t)/dp``, the state's Jacobian with respect to the initial conditions (eq. 5.4-5.5), is
  exact: forward-mode automatic differentiation through :func:`torchfit.dynamics.integrate`'s
  fixed-step RK4, all parameters at once (the batch holds one copy of the parameters per
  tangent). That is the paper's "integrate the variational equations with RK4, fixed step"
  differentiated after discretisation. Gravity enters the same way: its direction (tilt,
  roll) changes only the state, so its column comes from the same pass (the paper took it by
  finite differences; through the integrator it is exact and costs nothing extra).
* ``dS(t)/dq(t)``, the silhouette's derivative with respect to the pose (the silhouette depends
  on position and orientation only, as the paper notes), by central finite differences in
  image space (eq. 5.6): each of the six pose components (position x, y, z in metres and a
  world-frame rotation vector in radians) is moved by ``± h``, the hard silhouette re-rendered,
  and the two images differenced. All 12 perturbations of all frames and the unperturbed
  frames go through one render call. Then ``dE/dq(t) = Σ_px 2 (S - S_obs) dS/dq(t)``.

Parameters ``p`` (14): the centre of mass's position (3) and velocity (3) at t = 0, the
orientation as a rotation vector (3) about the current quaternion (folded in after every
step), the angular velocity (3, world frame) and the gravity direction's tilt and roll (2);
the magnitude ``g`` is known. This is the paper's ``q(t0)`` plus the gravity direction.

Update (eq. 5.2): plain gradient descent ``p ← p − λ ĝ`` with ``λ`` "the magnitude of the step in
the gradient direction" (the paper's words), taken in scaled units (see :func:`parameter_scales`:
one unit of each parameter moves the silhouette by about the object's radius over the clip).
The paper gives no rule for ``λ``; here a simple backtracking: if the loss does not decrease,
halve ``λ`` and try again (up to ``max_backtracks`` times); after an accepted step grow it by
``grow``. The descent stops after ``iterations`` gradient evaluations, or when ``λ`` falls below
``min_step`` (no descent direction found at any useful step).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor

from ..camera import tilt_roll_from_direction
from ..dynamics import integrate
from ..render import render_silhouettes
from ..rotation import axis_angle_to_quat, quat_multiply, quat_to_matrix
from ..search import Candidates, FitResult, Problem, rk4_step

__all__ = [
    "PARAMETERS",
    "PaperResult",
    "PaperSettings",
    "hard_loss",
    "hybrid_gradient",
    "paper_fit",
    "parameter_scales",
    "pose_jacobian",
]

# parameter layout of ``p`` (14,)
PARAMETERS = ("delta_x", "delta_y", "delta_z", "com_x", "com_y", "com_z", "vel_x", "vel_y", "vel_z",
              "omega_x", "omega_y", "omega_z", "tilt", "roll")


@dataclass(frozen=True)
class PaperSettings:
    """Knobs of the paper's gradient descent.

    Attributes:
        iterations: gradient evaluations (the fixed budget).
        step: initial ``λ``, scaled units (about the object's radius of silhouette motion).
        grow: factor on ``λ`` after an accepted step.
        max_backtracks: halvings of ``λ`` tried per iteration before giving up on it.
        min_step: stop when ``λ`` falls below this.
        fd_steps: finite-difference steps of the pose components: position x, y, z (metres,
            camera frame) and rotation about x, y, z (radians, camera frame). Hard silhouettes
            are piecewise constant, so a step must move edges by about a crop pixel.
        crop: side of the square crop window per frame, pixels (the windows of
            :meth:`Problem.windows` around the observed boxes).
    """

    iterations: int = 40
    step: float = 0.1
    grow: float = 1.5
    max_backtracks: int = 5
    min_step: float = 1e-3
    fd_steps: tuple = (0.005, 0.005, 0.02, 0.03, 0.03, 0.03)
    crop: int = 48

    def __post_init__(self) -> None:
        object.__setattr__(self, "fd_steps", tuple(float(h) for h in self.fd_steps))
        if len(self.fd_steps) != 6 or not all(h > 0 for h in self.fd_steps):
            raise ValueError(f"fd_steps must be six positive steps (x, y, z in m; rx, ry, rz in rad), got {self.fd_steps}")
        if int(self.iterations) < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        if not (self.step > 0 and self.grow >= 1 and self.min_step > 0 and self.max_backtracks >= 0):
            raise ValueError("need step > 0, grow >= 1, min_step > 0, max_backtracks >= 0, got "
                             f"{self.step}, {self.grow}, {self.min_step}, {self.max_backtracks}")
        if int(self.crop) < 8:
            raise ValueError(f"crop must be at least 8 pixels, got {self.crop}")


@dataclass
class PaperResult:
    """What :func:`paper_fit` found.

    Attributes:
        candidates: the best parameters seen (one candidate).
        state: (13,) user-convention initial state (mesh origin, quaternion, velocity, spin).
        gravity: (3,) gravitational acceleration, camera frame, m/s².
        loss: the hard loss of ``state``.
        loss_curve: the loss after each iteration (index 0: the initial guess).
        seconds: wall time of the descent.
        cpu_seconds: processor time of the descent (this process, all threads).
        iterations: gradient evaluations done.
        evaluations: loss evaluations done (line search included).
    """

    candidates: Candidates
    state: Tensor
    gravity: Tensor
    loss: float
    loss_curve: list
    seconds: float
    cpu_seconds: float
    iterations: int
    evaluations: int

    def as_fit_result(self) -> FitResult:
        """The result as a one-candidate :class:`FitResult` (for :func:`torchfit.report.score_against_truth`)."""
        history = [("paper gradient descent", self.seconds, self.loss, 1)]
        return FitResult(self.candidates, torch.tensor([self.loss], dtype=self.state.dtype),
                         self.state[None], history, list(self.loss_curve), {})


def parameter_scales(problem: Problem) -> Tensor:
    """(14,) the size of one scaled unit of each parameter.

    One unit moves the silhouette by about the object's radius ``r`` by the end of the clip
    (duration ``T``): rotation 1 rad, position ``r``, velocity ``r / T``, spin ``1 / T``, gravity
    angle ``r / (½ g T²)``.
    """
    radius = float(problem.shape.radius)
    duration = max(float(problem.times[-1] - problem.times[0]), 1e-3)
    values = [1.0] * 3 + [radius] * 3 + [radius / duration] * 3 + [1.0 / duration] * 3 + \
        [radius / (0.5 * problem.g * duration**2)] * 2
    return torch.tensor(values, dtype=problem.times.dtype, device=problem.times.device)


def _candidates(base: Tensor, params: Tensor) -> Candidates:
    """Candidates from (B, 4) base quaternions and (B, 14) parameters."""
    return Candidates(base, params[:, 0:3], params[:, 3:6], params[:, 6:9], params[:, 9:12], params[:, 12:14])


def _step_size(problem: Problem, omega: Tensor) -> float:
    """The RK4 step of :func:`torchfit.search.candidate_losses`: at most 0.2 rad of turn per step."""
    return rk4_step(problem, omega, problem.times)


def _trajectory(problem: Problem, base: Tensor, params: Tensor, step: float):
    cands = _candidates(base, params)
    return integrate(cands.state(problem.body), problem.times, problem.body, cands.gravity(problem.g),
                     step_size=step)


def pose_jacobian(problem: Problem, base: Tensor, params: Tensor, scales: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The poses along the trajectory and their Jacobian w.r.t. the parameters (forward-mode AD).

    Args:
        base: (4,) quaternion the rotation-vector parameters act on.
        params: (14,) parameters (layout :data:`PARAMETERS`).
        scales: (14,) the Jacobian is taken w.r.t. ``params / scales`` (default: ones).

    Returns:
        com: (T, 3) centre-of-mass positions, camera frame, metres.
        rot: (T, 3, 3) rotations.
        jacobian: (T, 6, 14) derivative of (centre of mass, world-frame rotation vector about
            the current orientation) at each frame w.r.t. the (scaled) parameters.
    """
    n = params.shape[0]
    tangents = torch.diag(scales if scales is not None else torch.ones_like(params))
    step = _step_size(problem, params[9:12])
    with fwAD.dual_level():
        dual = fwAD.make_dual(params.detach().expand(n, n).clone(), tangents)
        traj = _trajectory(problem, base.expand(n, 4), dual, step)
        quat = traj.quat
        com = fwAD.unpack_dual(traj.position + (quat_to_matrix(quat) @ problem.body.com.unsqueeze(-1)).squeeze(-1))
        primal_quat = fwAD.unpack_dual(quat).primal
        conj = primal_quat * primal_quat.new_tensor([1.0, -1.0, -1.0, -1.0])
        # q(t, p) ⊗ q(t, p₀)⁻¹ is the identity at p₀; twice its vector part has the derivative
        # of the world-frame rotation vector there
        d_rotvec = fwAD.unpack_dual(2.0 * quat_multiply(quat, conj)[..., 1:]).tangent
        jacobian = torch.cat((com.tangent, d_rotvec), -1)  # (14, T, 6)
        com_track = com.primal[0].clone()
        rot = quat_to_matrix(primal_quat[0])
    return com_track, rot, jacobian.permute(1, 2, 0)


def _render(problem: Problem, rot: Tensor, position: Tensor, crop: int) -> Tensor:
    """(B, T, crop, crop) hard silhouettes of (B, T) poses in the frames' crop windows."""
    windows = problem.windows(crop).expand(rot.shape[0], -1, 3)
    return render_silhouettes(problem.mesh, problem.camera, rot, position, windows, size=(crop, crop), sigma=None)


def _frame_weights(problem: Problem, dtype) -> Tensor:
    used = problem.used.to(dtype)
    return used / used.sum().clamp(min=1.0)


def hard_loss(problem: Problem, base: Tensor, params: Tensor, crop: int) -> Tensor:
    """(B,) the paper's objective (eq. 5.1) for (B, 14) parameters about (B, 4) base quaternions.

    Mean over used frames of the mean over crop pixels of ``(S_sim - S_obs)²``, with hard
    simulated silhouettes and the observed coverage resampled to the crop.
    """
    with torch.no_grad():
        traj = _trajectory(problem, base, params, _step_size(problem, params[:, 9:12]))
        cover = _render(problem, traj.rot, traj.position, crop)
        per_frame = (cover - problem.targets(crop)).square().mean(dim=(-2, -1))  # (B, T)
        loss = per_frame @ _frame_weights(problem, per_frame.dtype)
    return torch.where(torch.isfinite(loss), loss, torch.full_like(loss, float("inf")))


def hybrid_gradient(problem: Problem, base: Tensor, params: Tensor, settings: PaperSettings,
                    scales: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The paper's hybrid gradient (eq. 5.3) of :func:`hard_loss` at one point.

    Args:
        base: (4,) quaternion; params: (14,) parameters.
        scales: (14,) the gradient is w.r.t. ``params / scales`` (default: ones).

    Returns:
        loss: () the hard loss at ``params``.
        gradient: (14,) ``dE/dp``.
    """
    crop = int(settings.crop)
    com_track, rot, jacobian = pose_jacobian(problem, base, params, scales)  # (T, 3), (T, 3, 3), (T, 6, 14)
    steps = com_track.new_tensor(settings.fd_steps)  # (6,)
    signed = torch.cat((torch.zeros(1, 6, dtype=steps.dtype, device=steps.device), torch.diag(steps),
                        -torch.diag(steps)))  # (13, 6): none, then +h and -h per pose component
    turned = quat_to_matrix(axis_angle_to_quat(signed[:, 3:]))[:, None] @ rot[None]  # (13, T, 3, 3)
    # positions are the centre of mass's, so a rotation turns the body about its centre of mass
    origin = com_track[None] + signed[:, None, :3] - turned @ problem.body.com  # (13, T, 3)
    with torch.no_grad():
        cover = _render(problem, turned, origin, crop)  # (13, T, h, w)
    residual = cover[0] - problem.targets(crop)  # (T, h, w)
    weights = _frame_weights(problem, residual.dtype)  # (T,)
    loss = (residual.square().mean(dim=(-2, -1)) * weights).sum()
    d_cover = (cover[1:7] - cover[7:13]) / (2.0 * steps[:, None, None, None])  # (6, T, h, w)
    d_loss_d_pose = (2.0 * residual[None] * d_cover).mean(dim=(-2, -1)) * weights  # (6, T)
    gradient = torch.einsum("kt,tkp->p", d_loss_d_pose, jacobian)
    return loss, gradient


def paper_fit(problem: Problem, initial_state: Tensor, gravity_dir: Tensor, settings: PaperSettings = PaperSettings(),
              progress: Callable[[str], None] | None = None) -> PaperResult:
    """Gradient descent on the hard silhouette loss from a given guess (the paper's method).

    Args:
        problem: the observation as tensors.
        initial_state: (13,) guess at t = 0 (mesh-origin position, quaternion wxyz, mesh-origin
            velocity, angular velocity), camera frame.
        gravity_dir: (3,) guess of the gravity direction, camera frame (normalised here).
        settings: the descent's knobs.
        progress: called with one-line status messages.

    Returns:
        The best parameters seen, as a :class:`PaperResult`.

    Raises:
        ValueError: a guess of the wrong shape or not finite.
    """
    dtype, device = problem.times.dtype, problem.times.device
    state = torch.as_tensor(initial_state, dtype=dtype, device=device)
    direction = torch.as_tensor(gravity_dir, dtype=dtype, device=device)
    if state.shape != (13,) or not bool(torch.isfinite(state).all()):
        raise ValueError(f"initial_state must be 13 finite numbers, got shape {tuple(state.shape)}")
    if direction.shape != (3,) or not float(direction.norm()) > 0:
        raise ValueError(f"gravity_dir must be a non-zero (3,) vector, got {direction.tolist()}")
    say = progress or (lambda message: None)
    clock, cpu_clock = time.perf_counter(), time.process_time()
    body = problem.body
    quat = state[3:7] / state[3:7].norm()
    lever = quat_to_matrix(quat) @ body.com
    omega = state[10:13]
    tilt, roll = tilt_roll_from_direction(direction)
    params = torch.cat((torch.zeros(3, dtype=dtype, device=device), state[0:3] + lever,
                        state[7:10] + torch.cross(omega, lever, dim=-1), omega, torch.stack((tilt, roll))))
    base = quat
    scales = parameter_scales(problem)
    lam = float(settings.step)
    loss = float(hard_loss(problem, base[None], params[None], settings.crop)[0])
    curve = [loss]
    evaluations, done = 1, 0
    for iteration in range(int(settings.iterations)):
        if lam < settings.min_step:
            break
        _, gradient = hybrid_gradient(problem, base, params, settings, scales)  # w.r.t. scaled params
        done += 1
        norm = float(gradient.norm())
        if not math.isfinite(norm) or norm == 0.0:
            say(f"paper: iteration {iteration + 1}: zero or invalid gradient, stopping")
            break
        direction_scaled = gradient / norm
        accepted = False
        for _ in range(int(settings.max_backtracks) + 1):
            trial = params - lam * direction_scaled * scales
            trial_loss = float(hard_loss(problem, base[None], trial[None], settings.crop)[0])
            evaluations += 1
            if trial_loss < loss:
                accepted = True
                break
            lam *= 0.5
        if accepted:
            new_base = quat_multiply(axis_angle_to_quat(trial[0:3]), base)
            base = new_base / new_base.norm()
            params = torch.cat((torch.zeros_like(trial[0:3]), trial[3:]))
            loss = trial_loss
            lam *= settings.grow
        curve.append(loss)
        if iteration % 10 == 0 or iteration == settings.iterations - 1:
            say(f"paper: iteration {iteration + 1}/{settings.iterations}, loss {loss:.5f}, step {lam:.4g}")
    cands = _candidates(base[None], params[None])
    with torch.no_grad():
        final_state = cands.state(body)[0]
        gravity = cands.gravity(problem.g)[0]
    return PaperResult(cands, final_state.detach(), gravity.detach(), loss, curve, time.perf_counter() - clock,
                       time.process_time() - cpu_clock, done, evaluations)
