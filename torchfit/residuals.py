"""Where a fit and a recording disagree: residual channels per frame against a noise floor.

A fitted silhouette can miss the observed one in five ways, each pointing at different physics:
its centroid is off sideways (``centroid_x``) or vertically (``centroid_y``) — forces such as drag,
lift or a tilted gravity; its size is off (``scale``) — depth, so motion along the line of sight;
or its outline is off at the same place and size, longer or shorter (``shape``) or turned in the
image plane (``orientation``) — the body's orientation, so torques, inertia or the centre of mass. Segmentation noise is nearly independent from frame to frame, while missing
physics grows smoothly with time; so the noise floor of each channel is estimated from the data
itself, from its frame-to-frame differences, and a channel carries a mismatch when a smooth trend
stands above that floor. Segmentation also errs smoothly — its edge bias follows the pose — so the
floor adds a systematic term for an edge accuracy of ``edge_px`` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .losses import mask_moments

__all__ = ["CHANNELS", "UNITS", "Residuals", "channel_values", "channel_trend", "huber_root", "locate",
           "noise_floor", "polynomial_trend", "residual_channels", "systematic_floor"]

CHANNELS = ("centroid_x", "centroid_y", "scale", "shape", "orientation")
UNITS = {"centroid_x": "px", "centroid_y": "px", "scale": "relative", "shape": "relative",
          "orientation": "relative"}


@dataclass(frozen=True)
class Residuals:
    """Observed minus fitted, per frame and channel.

    Attributes:
        times: (T,) seconds.
        used: (T,) frames that enter the statistics.
        values: channel name -> (T,) residual: centroid in pixels (x right, y down), ``scale``
            as log(observed size / fitted size) with size = sqrt(area), ``shape`` as the
            normalised second moments' difference along the observed outline's long axis
            (elongation; positive: the observed outline is longer and thinner), ``orientation``
            as the observed less the fitted cross moment in the observed outline's principal
            axes over the observed trace (≈ the in-plane turn in radians times (λ₁ − λ₂)/(λ₁ +
            λ₂): zero for a round outline, whose turn is unobservable). discover measures both
            along its baseline's outline's axes instead (:func:`channel_values`).
        noise: channel name -> noise floor (standard deviation, same unit as the channel).
    """

    times: np.ndarray
    used: np.ndarray
    values: dict
    noise: dict


def residual_channels(observed: np.ndarray | torch.Tensor, fitted: np.ndarray | torch.Tensor,
                      times: np.ndarray, used: np.ndarray | None = None, *,
                      edge_px: float = 0.5) -> Residuals:
    """Residual channels of fitted silhouettes against observed masks.

    Args:
        observed: (T, H, W) observed masks (bool or coverage).
        fitted: (T, H, W) fitted silhouettes (bool or coverage), same frames.
        times: (T,) seconds.
        used: (T,) frames to use (default: every frame where both silhouettes are non-empty).
        edge_px: systematic edge accuracy of the segmentation, pixels. 0.5 covers the shipped
            recordings: segmented against true masks, the T-handle's centroid differs by
            0.32 px RMS with a smooth, pose-dependent bias (tests/test_residuals.py).
    """
    observed = torch.as_tensor(np.asarray(observed), dtype=torch.float64)
    fitted = torch.as_tensor(np.asarray(fitted), dtype=torch.float64)
    if observed.shape != fitted.shape or observed.ndim != 3:
        raise ValueError(f"observed and fitted must both be (T, H, W), got {tuple(observed.shape)} "
                         f"and {tuple(fitted.shape)}")
    moments_o, moments_f = mask_moments(observed), mask_moments(fitted)
    visible = ((moments_o[0] > 0) & (moments_f[0] > 0)).numpy()
    used = visible if used is None else np.asarray(used, bool) & visible
    values = {name: np.where(used, value.numpy(), np.nan)
              for name, value in channel_values(moments_o, moments_f).items()}
    systematic = systematic_floor(observed.numpy() > 0.5, used, edge_px)
    noise = {name: float(np.hypot(noise_floor(value[used]), systematic[name]))
             for name, value in values.items()}
    return Residuals(np.asarray(times, float), used, values, noise)


def channel_values(observed: tuple, fitted: tuple, axis: torch.Tensor | None = None) -> dict:
    """The five channels from silhouette moments (differentiable in ``fitted``).

    Args:
        observed, fitted: ``(area (..., ), centroid (..., 2), covariance (..., 2, 2))`` in image
            pixels, as :func:`torchfit.losses.mask_moments` returns them; any batch shape.
        axis: (..., 2) unit vectors along which ``shape`` and ``orientation`` are measured; None
            takes the observed outline's long axis. Where ``observed`` moves with the fitted
            parameters (discover's edge nuisance), pass an axis that does not: a near-round
            outline's long axis turns by a quarter turn under the slightest change, and the
            channels then jump (on a synthetic ball, a cost of 605 by 0.06 where the edge
            term's ``b1`` crossed 0; experiments/discover/HISTORY.md *Thirty-eighth session*).

    Returns:
        channel name -> (...) residual, observed minus fitted (see :class:`Residuals`).
    """
    area_o, centre_o, cov_o = observed
    area_f, centre_f, cov_f = fitted
    safe_o, safe_f = area_o.clamp(min=1.0), area_f.clamp(min=1.0)
    # second moments per unit area: shape without size
    shape_o, shape_f = cov_o / safe_o[..., None, None], cov_f / safe_f[..., None, None]
    if axis is None:
        axis = torch.linalg.eigh(shape_o)[1][..., :, -1]  # (..., 2) the observed outline's long axis
    # the short axis a quarter turn from the long one: the cross moment is then the same for
    # either sign of the long axis (eigh's sign is arbitrary)
    short_axis = torch.stack((-axis[..., 1], axis[..., 0]), -1)

    def along(moments, other):
        return torch.einsum("...i,...ij,...j->...", axis, moments, other)

    return {
        "centroid_x": centre_o[..., 0] - centre_f[..., 0],
        "centroid_y": centre_o[..., 1] - centre_f[..., 1],
        "scale": 0.5 * torch.log(safe_o / safe_f),
        "shape": along(shape_o, axis) / along(shape_f, axis).clamp(min=1e-9) - 1.0,
        "orientation": (along(shape_o, short_axis) - along(shape_f, short_axis))
        / torch.diagonal(shape_o, dim1=-2, dim2=-1).sum(-1).clamp(min=1e-9),
    }


def systematic_floor(observed: np.ndarray, used: np.ndarray, edge_px: float = 0.5) -> dict:
    """Per channel, the residual an edge shifted by ``edge_px`` pixels makes.

    Such an edge moves the centroid by up to ``edge_px``, the size by ``edge_px * perimeter /
    (2 area)`` and the normalised moments by about twice that.

    Args:
        observed: (T, H, W) bool observed masks.
        used: (T,) frames to use.
    """
    inner = observed.copy()
    inner[:, 1:-1, 1:-1] &= observed[:, :-2, 1:-1] & observed[:, 2:, 1:-1] & observed[:, 1:-1, :-2] \
        & observed[:, 1:-1, 2:]
    perimeter = (observed & ~inner).sum((1, 2))
    area = observed.sum((1, 2))
    ratio = float(np.median(perimeter[used] / np.maximum(area[used], 1))) if used.any() else 0.0
    return {"centroid_x": edge_px, "centroid_y": edge_px, "scale": edge_px * ratio / 2, "shape": edge_px * ratio,
            "orientation": edge_px * ratio / 2}


def noise_floor(values: np.ndarray, rho: float = 0.0) -> float:
    """Robust standard deviation of the frame-to-frame jitter (a smooth trend does not count).

    Second differences of white noise of variance s^2 have variance 6 s^2, and remove a trend
    up to linear exactly and a quadratic one to a constant; the median absolute deviation makes
    the floor robust to a few bad frames. With ``rho`` the noise is taken as correlated from one
    frame to the next (AR(1), lag-one correlation ``rho``): its second differences then have
    variance (6 - 8 rho + 2 rho^2) s^2, and the floor is s.
    """
    if len(values) < 5:
        return float("nan")
    second = np.diff(values, 2)
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0 - 8.0 * rho + 2.0 * rho**2))


def huber_root(values: torch.Tensor, k: float) -> torch.Tensor:
    """``sign(r) sqrt(rho(r))`` of residuals ``r`` (any shape) in units of independent noise, with
    Huber's loss ``rho(r) = r^2`` for ``|r| <= k`` and ``2 k |r| - k^2`` beyond: the squares of
    the result sum to Huber's cost, so a least-squares solver, a chi-squared and a Gauss-Newton
    covariance of these values are Huber's (the "square-rooted" robust cost of Triggs et al.,
    *Bundle adjustment — a modern synthesis*, 2000). Residuals within ``k`` pass
    unchanged; a frame ``m`` noise units off counts ``2 k m - k^2`` instead of ``m^2`` (k = 2:
    36 instead of 100 at 10). Continuously differentiable; NaN stays NaN. Same shape as ``values``.
    """
    size = values.abs()
    return torch.where(size <= k, values, torch.sign(values) * torch.sqrt((2 * k * size - k * k).clamp(min=k * k)))


def polynomial_trend(times: np.ndarray, values: np.ndarray, sigma: float,
                     covariance: np.ndarray | None = None) -> dict:
    """The simplest polynomial trend of (N,) ``values`` at (N,) ``times`` (degree 0-2, BIC) and
    its significance (a z-score from the drop in chi-squared).

    The noise is independent with standard deviation ``sigma``, or has the (N, N) ``covariance``
    (then ``sigma`` is unused): the trend is fitted by generalised least squares, every chi-squared
    taken on the values and the polynomial's columns whitened by the covariance's Cholesky factor.
    Noise correlated from frame to frame, or a prediction's spread from its fitted parameters
    (one error shared by all its frames), then counts for what it is, not as independent frames
    that a smooth trend would stand out of.
    """
    n = len(values)
    if covariance is None:
        whiten = lambda x: x / sigma  # noqa: E731
    else:
        factor = np.linalg.cholesky(covariance)
        whiten = lambda x: np.linalg.solve(factor, x)  # noqa: E731
    white = whiten(values)
    best = None
    chi2_zero = float(np.sum(white**2))
    for degree in (0, 1, 2):
        if n <= degree + 2:
            break
        design = whiten(np.vander(times, degree + 1))  # (N, degree + 1), highest power first as np.polyval
        coeffs = np.linalg.lstsq(design, white, rcond=None)[0]
        chi2 = float(np.sum((white - design @ coeffs) ** 2))
        bic = chi2 + (degree + 1) * np.log(n)
        if best is None or bic < best["bic"]:
            best = {"degree": degree, "coefficients": coeffs.tolist(), "chi2": chi2, "bic": bic}
    if best is None:
        return {"degree": None, "significance": 0.0, "chi2_per_frame": chi2_zero / max(n, 1)}
    # how far the explained part stands above the noise: sqrt(chi2 drop) ~ a z-score
    best["significance"] = float(np.sqrt(max(chi2_zero - best["chi2"], 0.0)))
    best["chi2_per_frame"] = chi2_zero / n
    return best


def channel_trend(times: np.ndarray, values: np.ndarray, sigma: float, threshold: float = 5.0,
                  covariance: np.ndarray | None = None) -> dict:
    """One residual channel's trend, as :func:`locate` words it.

    Args:
        times: (N,) ascending times of the values.
        values: (N,) residuals.
        sigma: their noise standard deviation (the floor the RMS and the onset are measured in).
        threshold: the trend must explain more than this many noise standard deviations.
        covariance: (N, N) the values' covariance, which the trend and its significance are
            fitted under (:func:`polynomial_trend`); None: independent noise of ``sigma``.

    Returns:
        ``rms``, ``significance``, ``trend`` (degree), ``growth`` (in words), ``sign`` of the
        trend at the last time (+1, -1 or 0), ``onset`` (the first index from which the trend
        stays above two noise floors, or None) and ``flagged`` (significant, with an RMS above
        twice the noise).
    """
    trend = polynomial_trend(times, values, sigma, covariance)
    fitted = np.polyval(trend["coefficients"], times) if trend["degree"] is not None else np.zeros_like(times)
    above = np.abs(fitted) > 2 * sigma
    rms = float(np.sqrt(np.mean(values**2)))
    return {"rms": rms, "significance": trend["significance"], "trend": trend["degree"],
            "growth": {0: "constant", 1: "growing linearly", 2: "growing like t^2"}.get(trend["degree"], "-"),
            "sign": int(np.sign(fitted[-1])) if len(fitted) else 0,
            "onset": next((i for i in range(len(above)) if above[i:].all()), None),
            "flagged": bool(trend["significance"] > threshold and rms > 2 * sigma)}


# the words for a channel's observed outline against the model's, by the sign of the trend
_DIRECTIONS = {"centroid_x": {1: "right", -1: "left"}, "centroid_y": {1: "down", -1: "up"},
               "scale": {1: "larger (nearer)", -1: "smaller (farther)"},
               "shape": {1: "longer", -1: "shorter"},
               "orientation": {1: "turned clockwise", -1: "turned counter-clockwise"}}


# the same against a prediction: where the observed outline lies from the predicted one
_FROM_PREDICTED = {"centroid_x": {1: "right of", -1: "left of"}, "centroid_y": {1: "below", -1: "above"},
                   "scale": {1: "larger (nearer) than", -1: "smaller (farther) than"},
                   "shape": {1: "longer than", -1: "shorter than"},
                   "orientation": {1: "turned clockwise from", -1: "turned counter-clockwise from"}}


def locate_prediction(values: dict, held: np.ndarray, times: np.ndarray, noise: dict, backward: bool = False,
                      threshold: float = 5.0, covariance: dict | None = None,
                      noise_covariance: dict | None = None) -> dict:
    """Where a prediction of held-out frames misses, in numbers and in words: :func:`locate`'s rule
    on the predicted frames, the time counted from the fitted frames outward, each frame's
    residual over its floor: the noise's, with ``covariance`` the prediction's own spread added.
    The trend is fitted and judged under the two covariances together (:func:`polynomial_trend`):
    the prediction's spread is one error of its fitted parameters, shared by every frame it
    predicts, and the noise is correlated from frame to frame; neither is a smooth trend of
    independent frames.

    A model fitted to all frames can take an effect's signature into its own freedoms (a drag into
    the launch speed and gravity's tilt) and leave residuals at noise level; its prediction of a
    part it did not see carries the mismatch instead, growing away from the frames it saw. A
    prediction also carries its fitted parameters' spread, growing the same way, which a clip
    that hides nothing shows too.

    Args:
        values: channel name -> (T,) residuals (observed minus predicted) of a fit that did not
            see the ``held`` frames.
        held: (T,) bool, the predicted frames (one contiguous part).
        times: (T,) seconds.
        noise: channel name -> noise floor.
        backward: the part lies before the fitted frames (predicted backward): its time runs from
            its last frame to its first.
        threshold: a channel's trend must explain more than this many floors, and its RMS over
            the floors exceed 2 (:func:`channel_trend`), to be flagged.
        covariance: channel name -> (T, T) the prediction's covariance from its fitted parameters
            (channel units; only the rows and columns of the held frames with a residual are
            read), or None: none.
        noise_covariance: channel name -> (T, T) the noise's covariance (read as ``covariance``),
            or None: independent, of standard deviation ``noise[name]``.

    Returns:
        ``{"frames": [first, last], "channels": {name: {...}}, "flagged": [names], "summary": str}``;
        per channel ``rms``, ``largest`` (the largest absolute residual), ``noise``,
        ``spread_largest`` (the prediction's largest standard deviation there, 0 without
        ``covariance``), ``unit``,
        ``significance`` (of the trend over the floors, which decides ``flagged``), ``trend`` and
        ``growth`` (the miss's own, away from the fitted frames), ``flagged`` and, when flagged,
        ``words``.
    """
    idx = np.flatnonzero(held)
    if backward:
        idx = idx[::-1]
    t = np.abs(times[idx] - times[idx[0]]) if len(idx) else np.zeros(0)
    report, flagged, words = {}, [], []
    for name in CHANNELS:
        sigma = noise[name]
        part = values[name][idx]
        finite = np.isfinite(part)
        if not np.isfinite(sigma) or finite.sum() < 5:
            continue
        sigma = max(sigma, 1e-9)
        rows = np.ix_(idx[finite], idx[finite])
        own_cov = np.zeros((finite.sum(),) * 2) if covariance is None else covariance[name][rows]
        total = own_cov + (sigma**2 * np.eye(len(own_cov)) if noise_covariance is None
                           else noise_covariance[name][rows])
        floor = np.sqrt(np.diag(total))
        # decides, in floors; says how the miss itself grows, in the channel's units
        trend = channel_trend(t[finite], part[finite] / floor, 1.0, threshold, total / np.outer(floor, floor))
        shape = channel_trend(t[finite], part[finite], sigma, threshold, total)
        own = np.sqrt(np.diag(own_cov))  # the prediction's own spread, frame by frame
        largest = float(np.max(np.abs(part[finite])))
        report[name] = {"rms": shape["rms"], "largest": largest, "noise": sigma,
                        "spread_largest": float(own.max()), "unit": UNITS[name],
                        "significance": trend["significance"], "trend": shape["trend"], "growth": shape["growth"],
                        "flagged": trend["flagged"]}
        if trend["flagged"]:
            flagged.append(name)
            direction = _FROM_PREDICTED[name].get(shape["sign"], "off")
            growth = shape["growth"] + (" away from the fitted frames" if shape["trend"] else "")
            own_words = "" if covariance is None else f", the prediction's own spread up to {own.max():.2g}"
            report[name]["words"] = (f"{name} observed {direction} the prediction, {growth}, up to {largest:.3g} "
                                     f"{UNITS[name]} (noise floor {sigma:.2g}{own_words})")
            words.append(report[name]["words"])
    quiet = [name for name in report if name not in flagged]
    if quiet:
        words.append(f"at noise level: {', '.join(quiet)}")
    if not report:
        words.append(f"too few frames to tell ({len(idx)}; 5 needed)")
    frames = [int(idx.min()), int(idx.max())] if len(idx) else []
    return {"frames": frames, "channels": report, "flagged": flagged, "summary": "; ".join(words)}


def locate(residuals: Residuals, threshold: float = 5.0) -> dict:
    """Which channels and frames carry the mismatch, in numbers and in words.

    A channel is flagged when its smooth trend explains more than ``threshold`` noise standard
    deviations (a z-score from the drop in chi-squared) and its RMS exceeds twice the floor.

    Returns:
        ``{"channels": {name: {...}}, "flagged": [names], "summary": "one line per finding"}``;
        per channel: ``rms``, ``noise``, ``unit``, ``significance``, ``trend`` (degree), ``growth``
        (``constant``/``linear``/``like t^2``), ``from_frame`` (first frame from which the trend
        stays above two noise floors), ``flagged`` and, when flagged, ``words`` (its part of the summary).
    """
    idx = np.flatnonzero(residuals.used)
    t = residuals.times[idx] - residuals.times[idx[0]] if len(idx) else np.zeros(0)
    report, flagged, words = {}, [], []
    for name in CHANNELS:
        values = residuals.values[name][idx]
        sigma = residuals.noise[name]
        if not np.isfinite(sigma) or len(values) < 5:
            continue
        sigma = max(sigma, 1e-9)
        trend = channel_trend(t, values, sigma, threshold)
        onset = None if trend["onset"] is None else int(idx[trend["onset"]])
        report[name] = {"rms": trend["rms"], "noise": sigma, "unit": UNITS[name],
                        "significance": trend["significance"], "trend": trend["trend"],
                        "growth": trend["growth"], "from_frame": onset, "flagged": trend["flagged"]}
        if trend["flagged"]:
            flagged.append(name)
            direction = _DIRECTIONS[name].get(trend["sign"], "")
            start = f" from frame {onset} on" if onset is not None else ""
            report[name]["words"] = (f"{name}: observed {direction} than fitted{start}, {trend['growth']}; RMS "
                                     f"{trend['rms']:.3g} {UNITS[name]} vs noise {sigma:.2g} "
                                     f"({trend['significance']:.0f} sigma)")
            words.append(report[name]["words"])
    quiet = [name for name in report if name not in flagged]
    if quiet:
        words.append(f"at noise level: {', '.join(quiet)}")
    return {"channels": report, "flagged": flagged, "summary": "; ".join(words)}
