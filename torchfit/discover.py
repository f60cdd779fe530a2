"""Discover missing physics: forward selection over the effect library, judged against the noise.

The engine (:func:`select_effects`) is generic. A problem supplies its estimated noise variance,
its candidate effect names and one verb, ``fit(effects, warm) -> ModelFit``: fit the model with
those effects (warm-started from ``warm``) on all data, and again on the data minus a held-out part
to measure the prediction error there. The engine then

1. fits the baseline (no effect);
2. refits with each candidate added (an effect whose ``replaces`` names one in the model swaps it,
   e.g. ``wind`` for ``quadratic_drag``, and is tried only once that one is in);
3. scores each against the current model by the change in ``χ² = RSS / σ²`` (σ² the noise
   variance estimated from the data, not from the fit), the BIC ``χ² + k ln n``, a likelihood-ratio
   p-value and the held-out RMS;
4. adds the winner if it beats the noise (ΔBIC above a threshold *and* a better held-out
   prediction) with parameters its physics allows (a negative damping is something else in
   disguise, never named as damping) and, where the problem reports it, a fitted value that its
   own uncertainty puts as far from the null as the ΔBIC claims (the Wald statistic passes the
   same threshold: a refit that lowers χ² while its new parameter stays within a few standard
   errors of zero moved the shared parameters, not the effect); if a look-alike is within the BIC margin of the winner the step names both as
   indistinguishable and stops — the data cannot say which;
5. repeats until nothing beats the noise.

:func:`discover_points` is the pipeline for 3D point tracks (:mod:`torchfit.points`), writing
``discover.json`` and before/after residual pictures. A video discover plugs in by implementing
:class:`SelectionProblem` on silhouettes (see the module's README section in experiments/discover).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from scipy import stats

from .effects import EFFECTS
from .points import (
    POINT_EFFECTS,
    PointData,
    PointFit,
    PointModel,
    ballistic_start,
    fit_tracks,
)
from .provenance import provenance
from .residuals import channel_trend

__all__ = [
    "ModelFit",
    "PointsProblem",
    "Selection",
    "SelectionProblem",
    "SelectionSettings",
    "Step",
    "discover_points",
    "estimate_noise",
    "fit_points",
    "locate_points",
    "plot_residuals",
    "select_effects",
    "alone_std",
    "bar_failures",
    "predictive_terms",
    "wald_statistic",
    "without_weakest_block",
]


@dataclass(frozen=True)
class SelectionSettings:
    """How forward selection decides.

    Attributes:
        min_delta_bic: a candidate must lower the BIC by more than this (10 = "very strong").
        min_heldout_gain: ...and improve the held-out RMS by at least this fraction,
        heldout_noise: ...or, when set, predict the held-out data within this RMS (in the units of
            ``ModelFit.heldout_rms``; on video, noise floors): a prediction at the noise level
            cannot be shown worse by held-out data, so the relative rule does not veto it.
        heldout_margin: when set, and the problem gives each fit's held-out predictive deviance
            (``ModelFit.heldout_deviance``), the held-out test is instead that the candidate's
            deviance exceeds the model it extends by at most this (2 ln of a Bayes factor against
            it; 6: "strong" evidence): the held-out error is judged against the prediction's own
            uncertainty, which an added parameter widens. Off by default: on the concealed video it
            named five right effects the RMS rule vetoes, and a lens on a control (HISTORY.md,
            twenty-first session).
        lookalike_margin: a passing candidate whose ΔBIC is within this of the winner's is a
            look-alike: both are reported as indistinguishable and none is added.
        max_effects: most effects added.
        holdout: fraction of each track (its end) held out for the prediction error.
        evidence_blocks: when above 1 and the problem reports each unit's chi-squared
            (``ModelFit.parts``: a video's frames), the units are cut into this many contiguous
            stretches, and a candidate must still lower the BIC (ΔBIC > 0) with any one stretch's
            share of its chi-squared change left out. A missing force acts over the whole
            flight; an error that follows the scene (a segmentation that errs while the object
            crosses one patch of background) lives in one stretch of it.
    """

    min_delta_bic: float = 10.0
    min_heldout_gain: float = 0.02
    heldout_noise: float | None = None
    heldout_margin: float | None = None
    lookalike_margin: float = 10.0
    max_effects: int = 4
    holdout: float = 0.25
    evidence_blocks: int = 1

    def __post_init__(self):
        if not 0 < self.holdout < 1:
            raise ValueError(f"holdout must be a fraction in (0, 1), got {self.holdout}")
        if self.evidence_blocks < 1:
            raise ValueError(f"evidence_blocks must be >= 1 (1: off), got {self.evidence_blocks}")
        if self.max_effects < 0:
            raise ValueError(f"max_effects must be >= 0, got {self.max_effects}")
        if self.heldout_margin is not None and not self.heldout_margin >= 0:
            raise ValueError(f"heldout_margin must be a deviance >= 0 (or None: off), got {self.heldout_margin}")


@dataclass
class ModelFit:
    """One fitted model, as the engine sees it.

    Attributes:
        effects: the effect names in the model.
        rss: sum of squared residuals on all data (data units², e.g. m²).
        n_obs: number of scalar observations.
        n_free: number of free parameters.
        params: ``{effect: {parameter: {"value", "std", "unit"}}}`` in physical units.
        fit_rms: RMS residual on all data.
        heldout_rms: RMS prediction error on the held-out part after fitting the rest.
        heldout_deviance: optional ``r^T S^-1 r + ln det S`` (:func:`predictive_terms`, summed) of
            the held-out part's residuals ``r``
            (in noise units) under the prediction's covariance ``S`` (noise plus the fit's own
            parameter uncertainty carried to the held-out part): -2 ln of its predictive density,
            up to a constant.
        heldout_logdet: optional ``ln det S``, the part of ``heldout_deviance`` that is the
            prediction's spread (the rest is its error against that spread).
        heldout_params: optional list, one ``{effect: {parameter: value}}`` per held-out split, of
            the fits whose predictions ``heldout_rms`` scores (physical units, as ``params``'
            values): the first fitted without the held-out end of the data, a second (a video's
            backcast) without its start.
        heldout_track_median: optional, for data in two or more tracks: the median over the tracks
            of each track's own held-out RMS (the mean over the splits, as ``heldout_rms``). The
            pooled ``heldout_rms`` weighs every sample alike, so a few badly predicted tracks can
            dominate it; the median says what a typical track's prediction does. Reported, not
            used by the selection.
        payload: the problem's own (warm start, residuals).
        parts: optional (U,) chi-squared per unit of the data (a video's frames, in order), the
            part of ``rss / noise_var`` each unit contributes: where a candidate's evidence lies.
        wald: optional ``{effect: W}``, ``W = (theta - theta_null)^T C^-1 (theta - theta_null)``
            of each effect's parameters with their covariance ``C`` at this fit: the chi-squared
            the fit's own uncertainty says the effect is worth (see :func:`select_effects`).
    """

    effects: tuple[str, ...]
    rss: float
    n_obs: int
    n_free: int
    params: dict
    fit_rms: float
    heldout_rms: float
    payload: Any = None
    parts: np.ndarray | None = None
    wald: dict | None = None
    heldout_deviance: float | None = None
    heldout_logdet: float | None = None
    heldout_params: list[dict] | None = None
    heldout_track_median: float | None = None


class SelectionProblem(Protocol):
    """What :func:`select_effects` needs from a data set (points, or silhouettes)."""

    noise_var: float
    candidates: tuple[str, ...]

    def fit(self, effects: tuple[str, ...], warm: ModelFit | None) -> ModelFit:
        """Fit with these effects on all data and on the non-held-out part."""

    # optional: ``applicable(effects) -> bool`` (False skips a combination the data cannot see);
    # ``fit_many(effect_sets, warm) -> list[ModelFit]``, a round's fits at once (as ``fit`` of each)


@dataclass
class Step:
    """One round of forward selection."""

    base: tuple[str, ...]
    scores: dict = field(default_factory=dict)  # candidate -> figures
    added: str | None = None
    indistinguishable: list[str] = field(default_factory=list)


@dataclass
class Selection:
    """The result: ``verdict`` (effects added, in order), the rounds, and every fitted model."""

    verdict: list[str]
    steps: list[Step]
    fits: dict[tuple[str, ...], ModelFit]
    noise_var: float

    def chain(self) -> list[tuple[str, ModelFit]]:
        """The baseline, then the model after each added effect: ``(label, fit)`` pairs."""
        keys, labels = [()], ["baseline"]
        for name in self.verdict:
            keys.append(_with(keys[-1], name))
            labels.append(f"+ {name}")
        return [(label, self.fits[key]) for label, key in zip(labels, keys)]


def _criterion(fit: ModelFit, noise_var: float) -> tuple[float, float]:
    chi2 = fit.rss / noise_var
    return chi2, chi2 + fit.n_free * math.log(max(fit.n_obs, 2))


def _with(base: tuple[str, ...], name: str) -> tuple[str, ...] | None:
    """``base`` plus ``name`` (swapping what it replaces), or None if it adds nothing new.

    An effect that refines another (``wind`` refines ``quadratic_drag``) is tried only once the
    one it refines is in the model: with its extra freedom (a wind vector) it would otherwise
    mimic other missing forces (a steady "wind" soaks up part of a Magnus lift).
    """
    if name in base or any(name in EFFECTS[e].replaces for e in base):
        return None
    if EFFECTS[name].replaces and not any(e in base for e in EFFECTS[name].replaces):
        return None
    return tuple(e for e in base if e not in EFFECTS[name].replaces) + (name,)


def _outside_bounds(name: str, params: dict) -> list[str]:
    """Parameters fitted more than 3 standard errors outside what the effect's physics allows
    (e.g. a negative damping): such a fit is another effect in disguise, not this one."""
    outside = []
    for pname, (low, high) in EFFECTS[name].bounds.items():
        entry = params.get(pname)
        if entry is None or not isinstance(entry.get("value"), float):
            continue
        std = entry.get("std") or 0.0
        std = std if math.isfinite(std) else 0.0
        if entry["value"] + 3 * std < low or entry["value"] - 3 * std > high:
            outside.append(f"{pname}={entry['value']:.4g} outside [{low}, {high}]")
    return outside


def without_weakest_block(parts: Sequence[float], delta_bic: float, blocks: int) -> tuple[float, list[int]]:
    """A candidate's ΔBIC with the weakest of ``blocks`` contiguous stretches of its per-unit
    chi-squared change ``parts`` (U,) left out (the penalty unchanged), and that stretch's first and
    last unit."""
    parts = np.asarray(parts, dtype=float)
    stretches = np.array_split(np.arange(len(parts)), blocks)
    left = [delta_bic - float(parts[units].sum()) for units in stretches]
    weakest = int(np.argmin(left))
    return left[weakest], [int(stretches[weakest][0]), int(stretches[weakest][-1])]


def _spread(base: ModelFit, fit: ModelFit, d_bic: float, blocks: int) -> dict:
    """Where a candidate's evidence lies: its chi-squared change per unit (``unit_delta_chi2``)
    and, with ``blocks`` > 1, :func:`without_weakest_block` (``delta_bic_without_block``,
    ``weakest_block``). Empty when the problem reports no units."""
    if base.parts is None or fit.parts is None:
        return {}
    parts = np.asarray(base.parts) - np.asarray(fit.parts)
    out: dict = {"unit_delta_chi2": parts.tolist()}
    if blocks > 1 and len(parts) >= blocks:
        out["delta_bic_without_block"], out["weakest_block"] = without_weakest_block(parts, d_bic, blocks)
    return out


def wald_statistic(value: torch.Tensor, null: torch.Tensor, cov: torch.Tensor) -> float:
    """``(value - null)^T cov^+ (value - null)`` of (P,) parameters with (P, P) covariance (the
    pseudo-inverse, so a direction the data do not see adds nothing); NaN if any is not finite."""
    diff = (value - null).double()
    cov = cov.double()
    if not (torch.isfinite(diff).all() and torch.isfinite(cov).all()):
        return float("nan")
    return float(diff @ torch.linalg.pinv(cov, hermitian=True) @ diff)


def predictive_terms(resid: torch.Tensor, jac: torch.Tensor, cov: torch.Tensor) -> tuple[float, float]:
    """``(r^T S^-1 r, ln det S)`` with ``S = I + J C J^T``, the two terms of -2 ln the Gaussian
    predictive density of (N,) held-out residuals ``r`` in noise units (up to ``N ln 2 pi``), where
    ``J`` (N, P) is their Jacobian in the fit's parameters and ``C`` (P, P) those parameters'
    covariance from the fit that predicted them: the error against the prediction's spread, and
    the spread's own cost. Rows with a non-finite residual (a frame out of view) are left out.
    """
    good = torch.isfinite(resid)
    r, j = resid[good].double(), jac[good].double()
    spread = torch.eye(len(r), dtype=torch.float64, device=r.device) + j @ cov.double() @ j.T
    factor = torch.linalg.cholesky(spread)
    white = torch.linalg.solve_triangular(factor, r[:, None], upper=False)[:, 0]
    return float(white.square().sum()), float(2 * factor.diagonal().log().sum())


def alone_std(cov: torch.Tensor) -> torch.Tensor:
    """(P,) standard error of each of P parameters of one effect with the effect's others held
    fixed, from their (P, P) covariance (the rest of the model marginalised): ``1 / sqrt((C^+)_ii)``.

    The size an effect needs to pass is a statement about one parameter moving alone (a lens's
    k1 with k2 at its null): a pair as correlated as k1 and k2 has marginal errors several times
    larger than either one's alone (3.2 times on a concealed T-handle's lens), and a limit from
    those would call detectable lenses invisible.
    Equal to the marginal error for a one-parameter block; inf where the data do not see it.
    """
    precision = torch.linalg.pinv(cov.double(), hermitian=True).diagonal()
    return torch.where(precision > 0, precision.clamp(min=1e-300).rsqrt(), torch.full_like(precision, math.inf))


def _scaled(std, factor: float):
    """``std`` (a number or a list of numbers) times ``factor``; NaN where unknown."""
    if isinstance(std, (list, tuple)):
        return [float(v) * factor if v is not None else float("nan") for v in std]
    return float(std) * factor if std is not None else float("nan")


def select_effects(problem: SelectionProblem, settings: SelectionSettings = SelectionSettings(),
                   progress: Callable[[str], None] | None = None) -> Selection:
    """Forward selection of effects (module docstring), returning the :class:`Selection`."""
    say = progress or (lambda message: None)
    base = problem.fit((), None)
    fits = {(): base}
    say(f"baseline: rms {base.fit_rms:.4g}, held-out {base.heldout_rms:.4g}, "
        f"noise {math.sqrt(problem.noise_var):.4g}")
    verdict, steps = [], []
    while len(verdict) < settings.max_effects:
        step = Step(base=base.effects)
        chi_base, bic_base = _criterion(base, problem.noise_var)
        tried = [(name, effects) for name in problem.candidates for effects in [_with(base.effects, name)]
                 if effects is not None and getattr(problem, "applicable", lambda e: True)(effects)]
        fresh = list(dict.fromkeys(effects for _, effects in tried if effects not in fits))
        if fresh and hasattr(problem, "fit_many"):  # the round's fits side by side
            fits.update(zip(fresh, problem.fit_many(fresh, base)))
        for name, effects in tried:
            fit = fits.get(effects) or problem.fit(effects, base)
            fits[effects] = fit
            chi, bic = _criterion(fit, problem.noise_var)
            d_chi = chi_base - chi
            d_k = max(fit.n_free - base.n_free, 1)
            p_value = float(stats.chi2.sf(max(d_chi, 0.0), d_k))
            # NaN where either held-out RMS is not a number (no frame to predict): the test then fails
            gain = (1.0 - fit.heldout_rms / base.heldout_rms if base.heldout_rms > 0
                    else 0.0 if base.heldout_rms == 0 else math.nan)
            outside = _outside_bounds(name, fit.params.get(name, {}))
            spread = _spread(base, fit, bic_base - bic, settings.evidence_blocks)
            deviance = (None if settings.heldout_margin is None or fit.heldout_deviance is None
                        or base.heldout_deviance is None else fit.heldout_deviance - base.heldout_deviance)
            if deviance is not None:
                heldout_ok = deviance <= settings.heldout_margin
            else:
                heldout_ok = gain >= settings.min_heldout_gain or (
                    settings.heldout_noise is not None and fit.heldout_rms <= settings.heldout_noise)
            wald = (fit.wald or {}).get(name)
            wald_bic = None if wald is None else wald - d_k * math.log(max(fit.n_obs, 2))
            bar = bar_failures(bic_base - bic, wald_bic, settings.min_delta_bic)
            fails = [test for test, failed in (
                ("delta_bic", bar["delta_bic"]), ("unphysical", bool(outside)),
                ("evidence_spread", not spread.get("delta_bic_without_block", 1.0) > 0),
                ("heldout", not heldout_ok), ("wald", bar["wald"])) if failed]
            # a parameter moves chi-squared by about (value / std)^2: the size it needs to pass
            need = math.sqrt(max(settings.min_delta_bic + d_k * math.log(max(fit.n_obs, 2)), 0.0))
            step.scores[name] = {
                "detectable_above": {p: _scaled(entry.get("alone_std", entry.get("std")), need)
                                     for p, entry in fit.params.get(name, {}).items()},
                "model": list(effects), "delta_chi2": d_chi, "delta_dof": d_k, "delta_bic": bic_base - bic,
                "p_value": p_value, "sigma": float(stats.norm.isf(max(p_value, 1e-300))) if p_value < 0.5 else 0.0,
                "delta_loss": base.rss - fit.rss, "rms_before": base.fit_rms, "rms_after": fit.fit_rms,
                "heldout_rms_before": base.heldout_rms, "heldout_rms_after": fit.heldout_rms,
                "heldout_gain": gain, "heldout_deviance_before": base.heldout_deviance,
                "heldout_deviance_after": fit.heldout_deviance, "heldout_deviance_rise": deviance,
                "heldout_logdet_before": base.heldout_logdet, "heldout_logdet_after": fit.heldout_logdet,
                "heldout_params": ([split.get(name) for split in fit.heldout_params] if fit.heldout_params
                                   else None), "params": fit.params,
                "unphysical": outside, "wald_chi2": wald, "wald_delta_bic": wald_bic,
                **spread,
                "fails": fails, "passes": not fails,
            }
            say(f"  + {name}: ΔBIC {bic_base - bic:.1f}, held-out {base.heldout_rms:.4g} -> {fit.heldout_rms:.4g}")
        steps.append(step)
        passing = sorted((s["delta_bic"], n) for n, s in step.scores.items() if s["passes"])
        if not passing:
            break
        best_bic, winner = passing[-1]
        alike = [n for d, n in passing[:-1] if best_bic - d < settings.lookalike_margin]
        if alike:
            step.indistinguishable = [winner, *alike]
            say(f"  {' / '.join(step.indistinguishable)}: indistinguishable on this data; stopping")
            break
        step.added = winner
        verdict.append(winner)
        base = fits[_with(base.effects, winner)]
        say(f"added {winner}")
    return Selection(verdict, steps, fits, problem.noise_var)


def bar_failures(delta_bic: float, wald_delta_bic: float | None, bar: float) -> dict[str, bool]:
    """Whether a candidate fails the criterion's two tests against ``bar``
    (``SelectionSettings.min_delta_bic``): its ΔBIC, and its Wald statistic less its ``Δk ln n``
    (``wald_delta_bic``; None where the problem gives none, which then passes)."""
    return {"delta_bic": not delta_bic > bar, "wald": wald_delta_bic is not None and not wald_delta_bic > bar}


def estimate_noise(data: PointData, window: int = 7, degree: int = 2) -> float:
    """Measurement noise variance (m² per coordinate) from the data alone: residuals of a local
    polynomial (degree 2) in every window of ``window`` consecutive samples, each window's
    residual sum divided by its degrees of freedom. A flight's acceleration changes too slowly to
    matter over a few samples, so what remains is noise.
    """
    sums, dofs = 0.0, 0
    for b in range(data.batch):
        n = int(data.weights[b].sum())
        t = data.times[b, :n].numpy()
        x = data.positions[b, :n].numpy()
        for start in range(n - window + 1):
            tt = t[start:start + window] - t[start]
            design = np.vander(tt, degree + 1)
            coef, *_ = np.linalg.lstsq(design, x[start:start + window], rcond=None)
            sums += float(((x[start:start + window] - design @ coef) ** 2).sum())
            dofs += 3 * (window - degree - 1)
    if dofs == 0:
        raise ValueError(f"tracks too short to estimate the noise: need at least {window} samples")
    return sums / dofs


def track_median_rms(residual: torch.Tensor, weights: torch.Tensor) -> float:
    """The median over tracks of each track's RMS, from (B, T, 3) weighted ``residual`` (zero where
    ``weights`` is) and (B, T) ``weights``; tracks without a weighted sample are left out (NaN
    when none has one)."""
    counts = weights.sum(-1)
    has = counts > 0
    if not bool(has.any()):
        return math.nan
    per_track = torch.sqrt((residual ** 2).sum((-1, -2))[has] / (3 * counts[has]))
    return float(np.median(per_track.detach().cpu().numpy()))


class PointsProblem:
    """:class:`SelectionProblem` for 3D point tracks: effect parameters shared by all tracks.

    Args:
        data: the tracks (:func:`torchfit.points.batch_tracks`).
        area, mass, moment, g, up: the object and the world (:class:`torchfit.points.PointModel`).
        candidates: effect names to try (those in ``POINT_EFFECTS``; ``magnus`` and
            ``angular_drag`` need a spin — measured, or fitted per track for ``magnus``).
        holdout: fraction of each track's end held out.
        backcast: hold out each track's first ``holdout`` as well, predicted from a fit to the
            rest (as :class:`torchfit.discover_video.VideoProblem`'s ``backcast``): the held-out
            RMS is then the mean of the two parts'.
        noise_var: m²; estimated from the data when ``None``.
    """

    def __init__(self, data: PointData, *, area: float, mass: float, moment: float, g: float = 9.81,
                 up: int = 2, candidates: Sequence[str] = POINT_EFFECTS, holdout: float = 0.25,
                 backcast: bool = False, noise_var: float | None = None, step: float = 0.005, progress=None):
        bad = [c for c in candidates if c not in POINT_EFFECTS]
        if bad:
            raise ValueError(f"candidates {bad} do not apply to point tracks; must be among {list(POINT_EFFECTS)}")
        if data.spin is None:
            candidates = [c for c in candidates if c != "angular_drag"]  # no spin, nothing to damp
        self.data = data
        self.candidates = tuple(candidates)
        self.kw = {"area": area, "mass": mass, "moment": moment, "g": g, "up": up, "spin_known": data.spin is not None, "step": step}
        # (train, held-out) of each split, named as the fits' payload keys: the end held out, and
        # with backcast the start
        end_train, end_test = data.split(1.0 - holdout)
        self.splits = {"train": (end_train, end_test)}
        if backcast:
            start_test, start_train = data.split(holdout)
            self.splits["train_backcast"] = (start_train, start_test)
        self.noise_var = float(noise_var) if noise_var is not None else estimate_noise(data)
        self.progress = progress

    def applicable(self, effects: Sequence[str]) -> bool:
        """Spin damping shows in a point track only through the Magnus force."""
        return "angular_drag" not in effects or "magnus" in effects

    def model(self, effects: Sequence[str]) -> PointModel:
        return PointModel(effects, **self.kw)

    def start(self, model: PointModel, warm: ModelFit | None, which: str) -> torch.Tensor:
        values = {}
        if warm is not None:
            old: PointFit = warm.payload[which]
            values = old.model.unpack(old.params)
            if "quadratic_drag" in old.model.effects and "wind" in model.effects:
                values[("wind", "drag_coefficient")] = values[("quadratic_drag", "drag_coefficient")]
        else:
            ballistic = ballistic_start(self.data if which == "all" else self.splits[which][0], model.gravity)
            values = {("", "p0"): ballistic[:, :3], ("", "v0"): ballistic[:, 3:]}
        if model.fit_spin and ("magnus", "spin") not in values:
            values[("magnus", "spin")] = torch.full((self.data.batch, 3), 1.0, dtype=torch.float64)
        return model.pack(values, self.data.batch)

    def fit(self, effects: tuple[str, ...], warm: ModelFit | None) -> ModelFit:
        model = self.model(effects)
        clock = time.perf_counter()
        full = fit_tracks(model, self.data, self.start(model, warm, "all"), shared=True)
        fits, split_rms, split_median = {"all": full}, [], []
        for which, (train_data, test_data) in self.splits.items():
            fits[which] = train = fit_tracks(model, train_data, self.start(model, warm, which), shared=True)
            held = train.residual * test_data.weights.unsqueeze(-1)
            split_rms.append(math.sqrt(float((held ** 2).sum()) / max(3 * float(test_data.weights.sum()), 1.0)))
            split_median.append(track_median_rms(held, test_data.weights))
        if self.progress:
            self.progress(f"    fit {list(effects)}: {time.perf_counter() - clock:.1f} s")
        heldout_params = [{name: {p: entry["value"] for p, entry in params.items()}
                           for name, params in self.describe(fits[which]).items()} for which in self.splits]
        return ModelFit(effects, full.rss, full.n_obs, full.n_free, self.describe(full),
                        math.sqrt(full.rss / full.n_obs), float(np.mean(split_rms)), fits,
                        wald=self.wald(full), heldout_params=heldout_params,
                        heldout_track_median=(float(np.mean(split_median)) if self.data.batch > 1 else None))

    def wald(self, fit: PointFit) -> dict:
        """``{effect: W}``: the Wald statistic of each effect's shared parameters against their null
        values (:func:`wald_statistic`, the covariance scaled as in :meth:`describe`); effects
        without shared parameters or covariance are left out. An effect's columns are contiguous."""
        if fit.shared_covariance is None:
            return {}
        nulls: dict = {}
        for name, pname, size in fit.model.columns[fit.model._first_effect():]:
            nulls.setdefault(name, []).append(
                torch.as_tensor(EFFECTS[name].null_params[pname], dtype=torch.float64).reshape(-1).expand(size))
        spans, local = self._spans(fit), fit.model.n_local
        return {name: wald_statistic(fit.params[0, a:b], torch.cat(nulls[name]),
                                     fit.shared_covariance[a - local:b - local, a - local:b - local] * self._variance(fit))
                for name, (a, b) in spans.items()}

    @staticmethod
    def _spans(fit: PointFit) -> dict:
        """``{effect: (first, end)}``: each effect's contiguous columns of ``fit.params``."""
        spans, col = {}, fit.model.n_local
        for name, _, size in fit.model.columns[fit.model._first_effect():]:
            spans[name] = (spans.get(name, (col,))[0], col + size)
            col += size
        return spans

    def _variance(self, fit: PointFit) -> float:
        """The larger of the estimated noise variance and the residual variance per degree of
        freedom (model misfit counts as noise): what the fit's covariance is scaled by."""
        return max(self.noise_var, fit.rss / max(fit.n_obs - fit.n_free, 1))

    def describe(self, fit: PointFit) -> dict:
        """Effect parameters with standard errors, in physical units.

        The standard error scales the fit's covariance by :meth:`_variance`.
        """
        variance = self._variance(fit)
        out: dict = {}
        spans, local = self._spans(fit), fit.model.n_local
        col = local
        for name, pname, size in fit.model.columns[fit.model._first_effect():]:
            value = fit.params[0, col:col + size]
            if fit.shared_covariance is not None:
                start, (a, b) = col - local, spans[name]
                cov = fit.shared_covariance * variance
                std = torch.sqrt(torch.diagonal(cov[start:start + size, start:start + size]).clamp(min=0))
                alone = alone_std(cov[a - local:b - local, a - local:b - local])[col - a:col - a + size]
            else:
                std = alone = torch.full((size,), float("nan"), dtype=torch.float64)
            entry = {"value": value.tolist() if size == 3 else float(value),
                     "std": std.tolist() if size == 3 else float(std),
                     "alone_std": alone.tolist() if size == 3 else float(alone),
                     "unit": EFFECTS[name].units.get(pname, "")}
            out.setdefault(name, {})[pname] = entry
            col += size
        if fit.model.fit_spin:
            spins = fit.params[:, 6:9]
            out.setdefault("magnus", {})["spin"] = {
                "value": spins.tolist(), "unit": "rad/s per track (with lift_coefficient fixed to 1)"}
        return out


def locate_points(fit: PointFit, data: PointData, noise_var: float, bins: int = 4, threshold: float = 5.0) -> dict:
    """Where a model's residual (observed minus predicted) lives: per world axis, per flight
    direction (along the velocity, the normal within the vertical plane, the lateral), and per
    stretch of the flight, each as an RMS in metres next to the noise's; and in words, per
    flight direction, as :func:`torchfit.residuals.locate` says it for video: the simplest
    polynomial trend in the time since each track's start (pooled over the tracks), flagged when
    it explains more than ``threshold`` noise standard deviations and the RMS exceeds twice the
    noise, with its sign, growth and the time from which it stays above two noise floors.
    """
    residual = fit.residual * data.weights.unsqueeze(-1)
    weights = data.weights
    count = float(weights.sum())
    rms = lambda r, w: math.sqrt(float((r ** 2).sum()) / max(float(w.sum()), 1.0))
    axes = {name: rms(residual[..., i], weights) for i, name in enumerate("xyz")}
    predicted = data.positions - fit.residual
    velocity = torch.gradient(predicted, dim=1)[0]
    along = velocity / velocity.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    up = -fit.model.gravity / fit.model.gravity.norm()
    lateral = torch.cross(along, up.expand_as(along), dim=-1)
    lateral = lateral / lateral.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    normal = torch.cross(lateral, along, dim=-1)
    components = {name: (residual * d).sum(-1)
                  for name, d in (("along_velocity", along), ("vertical_normal", normal), ("lateral", lateral))}
    directions = {name: rms(c, weights) for name, c in components.items()}
    progress = torch.cumsum(weights, -1) / weights.sum(-1, keepdim=True)
    stretches = {}
    for k in range(bins):
        inside = weights * ((progress > k / bins) & (progress <= (k + 1) / bins)).to(weights)
        stretches[f"{k / bins:.2f}-{(k + 1) / bins:.2f}"] = rms((residual ** 2).sum(-1).sqrt(), inside) / math.sqrt(3)
    sigma = math.sqrt(noise_var)
    kept = weights.flatten() > 0
    times = data.times.flatten()[kept].double().cpu().numpy()
    order = np.argsort(times, kind="stable")
    times = times[order]
    words, trends = [], {}
    # the sign of each direction in words: residual = observed - predicted
    sides = {"along_velocity": ("ahead of", "behind"), "vertical_normal": ("above", "below"),
             "lateral": ("right of", "left of")}
    for name, values in components.items():
        trend = channel_trend(times, values.flatten()[kept].double().cpu().numpy()[order], max(sigma, 1e-12),
                              threshold)
        onset = None if trend["onset"] is None else float(times[trend["onset"]])
        trends[name] = {"trend": trend["trend"], "growth": trend["growth"], "significance": trend["significance"],
                        "from_s": onset, "flagged": trend["flagged"]}
        if trend["flagged"]:
            side = sides[name][0 if trend["sign"] > 0 else 1]
            start = f" from {onset:.3g} s on" if onset is not None else ""
            words.append(f"{name.replace('_', ' ')}: observed {side} the fit{start}, {trend['growth']}; RMS "
                         f"{directions[name] * 1e3:.2f} mm vs noise {sigma * 1e3:.2f} mm "
                         f"({trend['significance']:.0f} sigma)")
    quiet = [name.replace("_", " ") for name in components if not trends[name]["flagged"]]
    if quiet:
        words.append(f"at noise level: {', '.join(quiet)}")
    return {
        "noise_rms_m": sigma, "rms_m": math.sqrt(float((residual ** 2).sum()) / (3 * count)),
        "axis_rms_m": axes, "direction_rms_m": directions, "stretch_rms_m": stretches,
        "direction_trends": trends, "summary": "; ".join(words),
    }


def plot_residuals(models: Sequence[tuple[str, PointFit]], data: PointData, path: Path, noise_var: float) -> None:
    """Residual channels (x, y, z) against time, one column per model (before / after)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(models), figsize=(3.6 * len(models), 6.5), sharex=True, sharey=True,
                             squeeze=False)
    noise = math.sqrt(noise_var) * 1e3
    alpha = 0.8 if data.batch <= 5 else max(0.08, 3.0 / data.batch)
    for col, (label, fit) in enumerate(models):
        for row in range(3):
            ax = axes[row, col]
            for b in range(data.batch):
                n = int(data.weights[b].sum())
                ax.plot(data.times[b, :n].numpy(), fit.residual[b, :n, row].numpy() * 1e3, lw=0.7, alpha=alpha)
            ax.axhspan(-noise, noise, color="0.85", zorder=0)
            ax.axhline(0, color="k", lw=0.5)
            if row == 0:
                ax.set_title(f"{label}\nrms {math.sqrt(fit.rss / fit.n_obs) * 1e3:.2f} mm", fontsize=9)
            if col == 0:
                ax.set_ylabel(f"{'xyz'[row]} residual (mm)")
            if row == 2:
                ax.set_xlabel("time (s)")
    fig.suptitle(f"observed - fitted position; grey band: ±noise ({noise:.2f} mm)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def spoken_unit(unit: str) -> str:
    """A parameter's unit as a report prints it: the SI ``1`` of a pure number is left out
    (``"1 (true fps / stated fps)"`` -> ``"(true fps / stated fps)"``); discover.json keeps it."""
    return unit[1:].strip() if unit == "1" or unit.startswith("1 (") else unit


def parameter_lines(verdict: Sequence[str], params: dict) -> list[str]:
    """``  effect.parameter = value ± std unit`` for every parameter of the named effects, from a
    model's ``params`` (``{effect: {parameter: {"value", "std", "unit"}}}``); a named effect the
    model no longer holds (quadratic drag once wind, with its own drag coefficient, replaced it)
    gets a line saying which later effect carries its parameters."""
    lines = []
    for k, name in enumerate(verdict):
        if name not in params:  # replaced by a later effect that carries the same parameter (wind's C_d)
            later = [n for n in verdict[k + 1:] if set(EFFECTS[n].null_params) & set(EFFECTS[name].null_params)]
            lines.append(f"  {name}: in the final model its parameters are {' and '.join(later) or 'another effect'}'s")
            continue
        for pname, entry in params.get(name, {}).items():
            value, std = entry["value"], entry["std"]
            if isinstance(value, list):
                text = "(" + ", ".join(f"{v:.4g}" for v in value) + ")"
                err = "(" + ", ".join(f"{s:.2g}" for s in std) + ")" if isinstance(std, list) else "?"
            else:
                text, err = f"{value:.4g}", f"{std:.2g}"
            lines.append(f"  {name}.{pname} = {text} ± {err} {spoken_unit(entry['unit'])}".rstrip())
    return lines


def physics_line(name: str) -> str:
    """An effect's physics in one line, as its class states it (the docstring's first line,
    e.g. ``quadratic_drag: Aerodynamic drag, quadratic in airspeed: F = -½ ρ C_d A |v| v``)."""
    first = (EFFECTS[name].__doc__ or "").strip().splitlines()[0].replace("``", "").rstrip(".")
    return f"  {name}: {first}"


def verdict_lines(selection: Selection, params: dict, label: str = "Verdict", explained: bool = True) -> list[str]:
    """The verdict in words, each named effect's physics (:func:`physics_line`), then the named
    effects' parameters (:func:`parameter_lines`). Look-alikes reported as indistinguishable get
    their physics too. ``explained``: False when the final model still leaves a mismatch above
    the noise. An empty verdict never says that nothing is missing, only that nothing was
    detected: an effect below the data's detection limits (:func:`limits_line`) is not ruled out."""
    if not selection.verdict:
        indist = [s.indistinguishable for s in selection.steps if s.indistinguishable]
        if indist:
            return [f"{label}: {' or '.join(indist[0])} — indistinguishable on this data; nothing named.",
                    *(physics_line(name) for name in indist[0])]
        if not explained:
            return [f"{label}: no effect of the library beats the noise."]
        return [f"{label}: nothing detected — no effect beats the noise (a smaller one is not ruled out)."]
    return [f"{label}: {', then '.join(selection.verdict)}.", *(physics_line(name) for name in selection.verdict),
            *parameter_lines(selection.verdict, params)]


def _size_text(values: np.ndarray, vector: bool) -> str:
    """A detection limit or a bound as the report prints it: ``(a, b, c)`` or ``a``, 2 digits."""
    return "(" + ", ".join(f"{v:.2g}" for v in values) + ")" if vector else f"{values[0]:.2g}"


def limits_line(selection: Selection, data: str, reach: dict | None = None,
                no_size: dict | None = None) -> list[str]:
    """What the first round could not have seen: each unnamed parameter's size below which it
    would not pass the criterion on this ``data`` ("clip", "tracks"), moving alone (the
    effect's other parameters at their null; :func:`alone_std`).

    ``no_size`` optionally maps an effect to why it has no such size on this data (a ball's
    lift, whose coefficient trades with a spin the video does not see); that is said instead.

    ``reach`` optionally gives, per ``"effect.parameter"``, the largest size the physics allows
    (a scalar, or one per component of a vector parameter, e.g. how far the body extends from its
    centre of mass for ``com_offset.offset``). A limit beyond it is said to be unobservable instead
    of quoted as a size no object could have.
    """
    reach, no_size = reach or {}, no_size or {}
    limits, unseen = [], []
    for name, score in (selection.steps[0].scores.items() if selection.steps else ()):
        if name in selection.verdict:
            continue
        if name in no_size:
            limits.append(f"{name}: no single size ({no_size[name]})")
            continue
        for pname, limit in score.get("detectable_above", {}).items():
            if limit is None:
                continue
            key = f"{name}.{pname}"
            unit = spoken_unit(EFFECTS[name].units.get(pname, ""))
            values, vector = np.atleast_1d(np.asarray(limit, dtype=float)), isinstance(limit, list)
            needed = f"±{_size_text(values, vector)} {unit}".rstrip()
            note = ""
            allowed = reach.get(key)
            if allowed is not None:
                allowed = np.broadcast_to(np.asarray(allowed, dtype=float), values.shape)
                beyond = values > allowed
                if beyond.all():
                    unseen.append(f"{key} (it would need {needed}; the physics allows ±{_size_text(allowed, vector)})")
                    continue
                if beyond.any():
                    axes = ", ".join("xyz"[i] if values.size == 3 else str(i) for i in np.flatnonzero(beyond))
                    note = f", along {axes} more than the physics allows (none there)"
            limits.append(f"{key} {needed}{note}")
    lines = []
    if limits:
        lines.append(f"What this {data} cannot rule out (a parameter smaller than this, the effect's others at "
                     "their null, would not pass the criterion): " + "; ".join(limits) + ".")
    if unseen:
        lines.append(f"Not observable on this {data} at any size the physics allows: " + "; ".join(unseen) + ".")
    return lines


def _train_values(name: str, score: dict) -> str:
    """``"; fitted without the held-out end its drag_coefficient reads 1.64, without the held-out
    start 0.93 (0.762 on all the data)"``: a candidate's scalar parameters as each fit that
    predicts a held-out part has them (the end's; a backcast's start's), beside the fit to all
    the data, so that a reader sees whether the effect or those fits went wrong; empty when the
    score has none."""
    params = score.get("params", {}).get(name, {})
    total = {p: entry["value"] for p, entry in params.items() if isinstance(entry.get("value"), (int, float))}
    splits = [{p: v for p, v in (split or {}).items() if p in total and isinstance(v, (int, float))}
              for split in score.get("heldout_params") or []]
    if not any(splits):
        return ""
    parts = [f"without the held-out {where} its " + ", ".join(f"{p} reads {v:.4g}" for p, v in split.items())
             for where, split in zip(("end", "start"), splits) if split]
    shown = [p for p in total if any(p in split for split in splits)]
    return "; fitted " + ", ".join(parts) + " (" + ", ".join(f"{total[p]:.4g}" for p in shown) + " on all the data)"


def not_named_lines(selection: Selection, heldout: Callable[[dict], str], spread: Callable[[dict], str],
                    no_values: Collection[str] = ()) -> list[str]:
    """Per round: every candidate that lowers the BIC by more than the threshold and is not
    named, with the tests it failed in words, then the round's three strongest candidates.
    ``heldout(score)`` words the held-out errors before -> after, ``spread(score)`` the stretch
    the evidence rests on; the effects in ``no_values`` are not quoted with their train fits'
    values (a ball's lift coefficient, which trades with its unseen spin)."""
    lines = []
    for step in selection.steps:
        for name, score in step.scores.items():
            fails = score.get("fails", [])
            if "delta_bic" in fails:
                continue
            reasons = []
            if "unphysical" in fails:
                reasons.append(f"its fit is unphysical ({'; '.join(score['unphysical'])}): another effect in disguise")
            if "heldout" in fails and score.get("heldout_deviance_rise") is not None:
                logdet = ("" if score.get("heldout_logdet_after") is None else
                          f", of which the prediction's spread {score['heldout_logdet_before']:.1f} -> "
                          f"{score['heldout_logdet_after']:.1f}")
                reasons.append(f"its held-out predictive deviance rises by {score['heldout_deviance_rise']:.1f} "
                               f"({heldout(score)}; deviance {score['heldout_deviance_before']:.1f} -> "
                               f"{score['heldout_deviance_after']:.1f}{logdet})")
            elif "heldout" in fails:
                values = "" if name in no_values else _train_values(name, score)
                reasons.append(f"it does not predict the held-out data well enough ({heldout(score)}, "
                               f"{100 * score['heldout_gain']:+.0f} %){values}")
            if "wald" in fails:
                reasons.append(f"its fitted value is within its own uncertainty of none (Wald chi2 "
                               f"{score['wald_chi2']:.1f} against a chi2 drop of {score['delta_chi2']:.1f}): the refit "
                               "moved the other parameters, not this effect")
            if "evidence_spread" in fails:
                reasons.append(f"its evidence rests on {spread(score)} (ΔBIC {score['delta_bic_without_block']:.1f} "
                               "without them): one stretch of the data, not a force over the whole flight")
            if reasons:
                lines.append(f"Not named: {name} lowers the BIC by {score['delta_bic']:.1f}, but " + "; and ".join(reasons) + ".")
        ranked = sorted(step.scores.items(), key=lambda kv: -kv[1]["delta_bic"])[:3]
        lines.append(f"Round {'+'.join(step.base) or 'baseline'}: " + "; ".join(
            f"{n} ΔBIC {s['delta_bic']:.1f}, held-out gain {100 * s['heldout_gain']:.0f}%" for n, s in ranked))
    return lines


def _track_median_words(base: ModelFit, final: ModelFit, mm: Callable[[float], str]) -> str:
    """The report's words for :attr:`ModelFit.heldout_track_median` before -> after (nothing when
    the fits do not carry it, e.g. a single track's)."""
    if base.heldout_track_median is None or final.heldout_track_median is None:
        return ""
    return f" (a track's, median over the tracks: {mm(base.heldout_track_median)} -> {mm(final.heldout_track_median)})"


def points_report(selection: Selection, chain: Sequence[ModelFit], located: dict, located_after: dict,
                  noise_var: float, holdout: float, backcast: bool = False) -> str:
    """report.txt of :func:`discover_points`: a report a person reads in a minute (``holdout``:
    the fraction at the end of each track that the held-out fits predict; ``backcast``: and at
    its start)."""
    base, final = chain[0], chain[-1]

    def mm(metres: float) -> str:
        return f"{metres * 1e3:.2f} mm"
    held_start = (f", and the first {100 * holdout:.0f} % predicted backward from the rest: the mean of the two"
                  if backcast else "")
    lines = [*verdict_lines(selection, final.params),
             f"Where the baseline misses (RMS {mm(located['rms_m'])}): {located['summary']}.",
             *limits_line(selection, "data"),
             f"Evidence: RMS {mm(base.fit_rms)} -> {mm(final.fit_rms)}; held-out RMS (the last "
             f"{100 * holdout:.0f} % of each track, predicted{held_start}) {mm(base.heldout_rms)} -> "
             f"{mm(final.heldout_rms)}{_track_median_words(base, final, mm)}; "
             f"BIC {_criterion(base, noise_var)[1]:.1f} -> {_criterion(final, noise_var)[1]:.1f}.",
             f"Left after the final model (RMS {mm(located_after['rms_m'])}): {located_after['summary']}.",
             *not_named_lines(selection, lambda s: f"{mm(s['heldout_rms_before'])} -> {mm(s['heldout_rms_after'])}",
                              lambda s: "one stretch of the samples")]
    return "\n".join(lines) + "\n"


def discover_points(data: PointData, *, area: float, mass: float, moment: float, g: float = 9.81, up: int = 2,
                    candidates: Sequence[str] = POINT_EFFECTS, settings: SelectionSettings = SelectionSettings(),
                    out_dir: Path | None = None, progress=None, step: float = 0.005,
                    backcast: bool = False) -> dict:
    """Discover missing physics in 3D point tracks; write ``discover.json`` and residual plots.

    Args:
        data: the tracks.
        area, mass, moment: the object's reference area (m²), mass (kg), moment of inertia (kg m²).
        g: m/s², along ``-up``.
        candidates: effects to try.
        settings: the selection rules.
        backcast: hold out each track's first ``settings.holdout`` as well, predicted backward
            (:class:`PointsProblem`).
        out_dir: where to write ``discover.json``, ``residuals.png`` and ``report.txt``
            (nothing written if None).

    Returns:
        The ``discover.json`` content (DESIGN.md): ``verdict``, ``effects``, ``located`` and more.
    """
    clock = time.perf_counter()
    problem = PointsProblem(data, area=area, mass=mass, moment=moment, g=g, up=up, candidates=candidates,
                            holdout=settings.holdout, backcast=backcast, step=step)
    selection = select_effects(problem, settings, progress)
    labelled = selection.chain()
    chain = [fit for _, fit in labelled]
    effects = {}
    for step_ in selection.steps:
        for name, score in step_.scores.items():
            effects.setdefault(name, []).append({"base": list(step_.base), **score})
    content = {
        "verdict": list(selection.verdict),
        "effects": effects,
        "located": locate_points(chain[0].payload["all"], data, problem.noise_var),
        "located_after": locate_points(chain[-1].payload["all"], data, problem.noise_var),
        "indistinguishable": [s.indistinguishable for s in selection.steps if s.indistinguishable],
        "noise_rms_m": math.sqrt(problem.noise_var),
        "models": [{"effects": list(f.effects), "rms_m": f.fit_rms, "heldout_rms_m": f.heldout_rms,
                    "heldout_track_median_m": f.heldout_track_median, "bic": _criterion(f, problem.noise_var)[1],
                    "n_obs": f.n_obs, "n_free": f.n_free, "params": f.params} for f in chain],
        "tracks": len(data.names),
        "samples": int(data.weights.sum()),
        "settings": asdict(settings),
        "backcast": backcast,
        "candidates": list(problem.candidates),
        "seconds": time.perf_counter() - clock,
        "provenance": provenance(),
    }
    content = _jsonable(content)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "discover.json").write_text(json.dumps(content, indent=1))
        plot_residuals([(label, f.payload["all"]) for label, f in labelled], data,
                       out_dir / "residuals.png", problem.noise_var)
        (out_dir / "report.txt").write_text(points_report(selection, chain, content["located"],
                                                          content["located_after"], problem.noise_var,
                                                          settings.holdout, backcast))
        content["figures"] = ["discover.json", "residuals.png", "report.txt"]
    return content


def fit_points(data: PointData, *, effects: Sequence[str] = (), area: float, mass: float, moment: float,
               g: float = 9.81, up: int = 2, out_dir: Path | None = None, step: float = 0.005) -> dict:
    """Fit a point-mass flight (gravity plus ``effects``) to 3D tracks; write ``result.json`` and
    ``residuals.png`` into ``out_dir``.

    Returns:
        ``{"params": {"position", "velocity", <effect>: {...}}, "per_frame": {"time", "observed",
        "fitted", "residual"}, "rms_m", "noise_rms_m", "loss"}`` (per track lists when B > 1).
    """
    problem = PointsProblem(data, area=area, mass=mass, moment=moment, g=g, up=up, candidates=(), step=step)
    model = problem.model(effects)
    start = problem.start(model, None, "all")
    if model.n_params > model.n_local:  # effects start from their classes' defaults, not from zero
        defaults = {(name, p): getattr(problem.model([name]).modules[name], p).detach()
                    for name in effects for p in EFFECTS[name].null_params}
        start = model.pack({**model.unpack(start), **defaults}, data.batch)
    fit = fit_tracks(model, data, start, shared=True)
    values = model.unpack(fit.params)
    per_frame = []
    for b in range(data.batch):
        n = int(data.weights[b].sum())
        fitted = data.positions[b, :n] - fit.residual[b, :n]
        per_frame.append({"time": data.times[b, :n].tolist(), "observed": data.positions[b, :n].tolist(),
                          "fitted": fitted.tolist(), "residual": fit.residual[b, :n].tolist()})
    one = data.batch == 1
    content = {
        "params": {"position": values[("", "p0")][0].tolist() if one else values[("", "p0")].tolist(),
                   "velocity": values[("", "v0")][0].tolist() if one else values[("", "v0")].tolist(),
                   "gravity": model.gravity.tolist(), **problem.describe(fit)},
        "per_frame": per_frame[0] if one else per_frame,
        "loss": fit.rss, "rms_m": math.sqrt(fit.rss / fit.n_obs), "noise_rms_m": math.sqrt(problem.noise_var),
        "effects": list(effects), "tracks": list(data.names),
    }
    content = _jsonable(content)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "result.json").write_text(json.dumps(content, indent=1))
        plot_residuals([("fit" + "".join(f" + {e}" for e in effects), fit)], data, out_dir / "residuals.png",
                       problem.noise_var)
    return content
