"""Scalar functions of time and time-series helpers of the motion planner.

Easing curves (:func:`_smoothstep`, :func:`_bump`, :func:`_ease`, :func:`_window`), tracks
through knots (:class:`_Track` / :func:`_keys`: monotone cubic, :class:`_Piecewise`,
:func:`_hermite`, linear :func:`_interp_extrap` / :func:`_interp_rows`), angle wrapping, the
True runs of a boolean array and a smooth upper envelope of a series.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, maximum_filter1d


def _smoothstep(s):
    """Quintic 0 -> 1 on [0, 1] with zero first and second derivatives at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def _bump(s):
    """0 at s = 0 and 1, peak 1 at s = 0.4, zero slope at both ends; the descent is gentler
    than the rise (a swinging foot lands softly)."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (1.0 - s) ** 3 / (0.4**2 * 0.6**3)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class _Track:
    """A scalar function of time through knots (t, value): monotone cubic (PCHIP), constant
    outside the knots. A single knot is a constant."""

    def __init__(self, knots):
        knots = sorted(knots, key=lambda k: k[0])
        ts = [knots[0][0]]
        vs = [knots[0][1]]
        for t, v in knots[1:]:
            if t - ts[-1] < 1e-9:  # a repeated time: the later value wins (a step is not allowed)
                vs[-1] = v
                continue
            ts.append(t)
            vs.append(v)
        self.t = np.array(ts, float)
        self.v = np.array(vs, float)
        self._f = PchipInterpolator(self.t, self.v, extrapolate=False) if len(ts) > 1 else None

    def __call__(self, t):
        t = np.asarray(t, float)
        if self._f is None:
            return np.full(t.shape, self.v[0])
        out = self._f(np.clip(t, self.t[0], self.t[-1]))
        return np.asarray(out, float)


def _keys(t, knots):
    """PCHIP track through (time, value) knots evaluated at t."""
    return _Track(knots)(t)


def _ease(t, t0, t1):
    """0 before t0, smooth rise to 1 at t1."""
    if t1 <= t0:
        return (np.asarray(t) >= t0).astype(float)
    return _smoothstep((np.asarray(t) - t0) / (t1 - t0))


def _window(t, t0, t1, ramp):
    """1 inside [t0 + ramp, t1 - ramp], smooth ramps to 0 at t0 and t1."""
    ramp = max(min(ramp, (t1 - t0) / 2), 1e-6)
    return _ease(t, t0, t0 + ramp) * (1.0 - _ease(t, t1 - ramp, t1))


def _runs(mask):
    """(start, stop) index pairs of the True runs of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0], strict=True))


def _interp_rows(t, tq, X):
    """Linear interpolation of the rows of X (sampled at t) at times tq."""
    X = np.asarray(X)
    flat = X.reshape(len(t), -1)
    out = np.stack([np.interp(tq, t, flat[:, i]) for i in range(flat.shape[1])], axis=-1)
    return out.reshape(np.shape(tq) + X.shape[1:])


def _smooth_upper(x, fps, width_s=0.12):
    """A smooth envelope >= x (dilate, then a truncated Gaussian of the dilation radius)."""
    k = max(1, int(round(width_s * fps)))
    S = gaussian_filter1d(maximum_filter1d(x, size=2 * k + 1, mode="nearest"), sigma=k / 3.0,
                          truncate=3.0, mode="nearest")
    return np.maximum(S, x)


def _interp_extrap(t, tp, fp):
    """Piecewise-linear interpolation, extrapolated linearly beyond the ends."""
    t = np.asarray(t, float)
    if len(tp) == 1:
        return np.full(t.shape, fp[0])
    out = np.interp(t, tp, fp)
    lo, hi = t < tp[0], t > tp[-1]
    out[lo] = fp[0] + (t[lo] - tp[0]) * (fp[1] - fp[0]) / (tp[1] - tp[0])
    out[hi] = fp[-1] + (t[hi] - tp[-1]) * (fp[-1] - fp[-2]) / (tp[-1] - tp[-2])
    return out


def _hermite(t, ta, tb, za, va, zb, vb):
    """Cubic Hermite from (za, va) at ta to (zb, vb) at tb."""
    L = tb - ta
    u = np.clip((np.asarray(t) - ta) / L, 0.0, 1.0)
    h00 = 2 * u**3 - 3 * u**2 + 1
    h10 = u**3 - 2 * u**2 + u
    h01 = -2 * u**3 + 3 * u**2
    h11 = u**3 - u**2
    return h00 * za + h10 * L * va + h01 * zb + h11 * L * vb


class _Piecewise:
    """A scalar function of time made of pieces (t0, t1, f); the last piece extends."""

    def __init__(self):
        self.pieces = []

    def add(self, t0, t1, f):
        self.pieces.append((t0, t1, f))
        return t1

    def __call__(self, t):
        t = np.asarray(t, float)
        out = np.zeros(t.shape)
        for i, (a, b, f) in enumerate(self.pieces):
            last = i == len(self.pieces) - 1
            m = (t >= a) & ((t < b) if not last else np.ones(t.shape, bool))
            if i == 0:
                m |= t < a
            if m.any():
                out[m] = f(t[m])
        return out


def _const(v):
    return lambda t: np.full(np.shape(t), float(v))


def _ramp(ta, tb, za, zb):
    return lambda t: za + (zb - za) * _smoothstep((np.asarray(t) - ta) / max(tb - ta, 1e-9))
