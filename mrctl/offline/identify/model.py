"""The LuGre force with constant Θ, vectorised over time and over parameter sets.

Why the model is vectorised across time although z is a state: the
exponential integrator of :mod:`mrctl.model.lugre` evaluates the relaxation
rate a = σ0·|v|/g(v) at the *velocity*, never at z, so with the velocity
record given, one step is the affine map z ← e_k·z + b_k with e_k, b_k
known for all k at once. A chain of affine maps is an associative product,
computed in log2(n) numpy passes (a Hillis–Steele scan). The result is the
same arithmetic as ``LuGreModel.advance`` (to rounding), for a whole batch of
parameter sets at once — which is what a finite-difference Jacobian needs.
See ``docs/identification.md`` for the optimiser comparison and measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

__all__ = ["THETA_NAMES", "THETA_UNITS", "lugre_force", "hys_state", "hys_columns"]

#: Per-current parameter vector Θ of eq (4), in this order (SI units).
THETA_NAMES: tuple[str, ...] = ("sigma0", "sigma1", "sigma2", "Fc", "Fs", "vs")
THETA_UNITS: dict[str, str] = {"sigma0": "N/m", "sigma1": "N·s/m", "sigma2": "N·s/m",
                               "Fc": "N", "Fs": "N", "vs": "m/s"}

# Below this a·h the integrator uses the series of φ1 (as LuGreModel does).
_SMALL_AH = 1e-8


def _exp_scan(e: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z_k = e_k·z_{k−1} + b_k along the last axis (z_{−1} = 0), in log2(n) passes.

    Element k holds the affine map of steps (k−span, k]; composing with the
    map ``span`` steps earlier doubles the span. All e_k ∈ [0, 1], so the
    running products only shrink: no overflow, and e_k = 0 resets the state
    (how separate windows share one array)."""
    E = e.copy()
    B = b.copy()
    n = E.shape[-1]
    s = 1
    while s < n:
        B[..., s:] += E[..., s:] * B[..., :-s]  # RHS is evaluated before the store
        E[..., s:] *= E[..., :-s]
        s *= 2
    return B


@dataclass
class _Record:
    """Precomputed, parameter-free arrays of one or more fit windows.

    Each window is warm-up samples followed by fit samples; the model state is
    reset at each window's first sample (to the steady-sliding z there)."""

    v: np.ndarray  # measured velocity at each sample (m/s)
    h: np.ndarray  # step to this sample from the previous one (s)
    reset: np.ndarray  # index of each window's first sample
    fit: np.ndarray  # indices of the samples in Q
    F: np.ndarray  # measured force at the fit samples (N)
    #: terms the force is linear in, at the fit samples (columns: 1 for an
    #: offset, x for a stiffness); None = the LuGre force alone
    X: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.Qx = np.linalg.qr(self.X)[0] if self.X is not None and self.X.size else None
        v = self.v
        vm = np.empty_like(v)
        vm[1:] = 0.5 * (v[1:] + v[:-1])  # mid-step velocity, as LuGreModel.advance
        vm[0] = v[0]
        self.vm = vm
        self.abs_vm = np.abs(vm)
        self.vm2 = vm * vm
        vf = v[self.fit]
        self.vf = vf
        self.abs_vf = np.abs(vf)
        self.vf2 = vf * vf
        self.v0 = v[self.reset]

    def project(self, R: np.ndarray) -> np.ndarray:
        """Residuals with the best linear terms removed (variable projection:
        an offset and a stiffness are solved exactly for every Θ)."""
        if self.Qx is None:
            return R
        return R - (R @ self.Qx) @ self.Qx.T

    def linear_terms(self, F_model: np.ndarray) -> np.ndarray:
        """The coefficients of X that best explain F − F_model (empty without X)."""
        if self.X is None:
            return np.zeros(0)
        return np.linalg.lstsq(self.X, self.F - F_model, rcond=None)[0]

    def with_terms(self, F_model: np.ndarray) -> np.ndarray:
        """F_model plus the best linear terms."""
        return F_model if self.X is None else F_model + self.X @ self.linear_terms(F_model)


def _model_batch(P: np.ndarray, rec: _Record, z0: float | None = None) -> np.ndarray:
    """Force at the fit samples for each row of P = [σ0, σ1, σ2, Fc, Fs, vs] (m × 6).

    Each window starts in steady sliding, z = sign(v)·g(v)/σ0 (the warm-up
    removes whatever error that leaves), unless ``z0`` is given."""
    P = np.atleast_2d(P)
    s0, s1, s2, Fc, Fs, vs = (P[:, j:j + 1] for j in range(6))
    c = 1.0 / (vs * vs)
    dF = Fs - Fc
    gm = Fc + dF * np.exp(-rec.vm2 * c)
    a = s0 * rec.abs_vm / gm
    x = a * rec.h
    small = x < _SMALL_AH
    xs = np.where(small, 1.0, x)
    phi1 = np.where(small, 1.0 - 0.5 * x, -np.expm1(-xs) / xs)  # (1 − e^{−x})/x
    e = np.exp(-x)
    b = rec.vm * rec.h * phi1
    e[:, rec.reset] = 0.0
    if z0 is None:
        v0 = rec.v0
        b[:, rec.reset] = np.sign(v0) * (Fc + dF * np.exp(-(v0 * v0) * c)) / s0
    else:
        b[:, rec.reset] = z0
    z = _exp_scan(e, b)[:, rec.fit]
    g = Fc + dF * np.exp(-rec.vf2 * c)
    zdot = rec.vf - s0 * rec.abs_vf * z / g
    return s0 * z + s1 * zdot + s2 * rec.vf


def lugre_force(theta: Sequence[float] | Mapping[str, float], v: np.ndarray, dt: float | np.ndarray,
                z0: float | None = None) -> np.ndarray:
    """Force (N) of the LuGre model with constant Θ driven by the velocity record v.

    ``theta`` is [σ0, σ1, σ2, Fc, Fs, vs] or a mapping of those names; ``dt``
    the sample interval (or the per-sample steps, h[0] unused). The tick
    protocol is :class:`mrctl.model.lugre.LuGreModel`'s: z advanced with the
    mid-step velocity, force at the sample's velocity. ``z0`` defaults to the
    steady-sliding state at v[0]."""
    if isinstance(theta, Mapping):
        theta = [theta[k] for k in THETA_NAMES]
    v = np.asarray(v, float).reshape(-1)
    n = v.size
    h = np.broadcast_to(np.asarray(dt, float), (n,)).astype(float)
    rec = _Record(v, h, np.array([0]), np.arange(n), np.zeros(n))
    return _model_batch(np.asarray(theta, float).reshape(1, 6), rec, z0)[0]


def hys_state(v: np.ndarray, h: float, x_hys: float, z0: float = 0.0) -> np.ndarray:
    """The hysteretic stiffness's state z_h at every sample (LuGreModel's exact step with the
    mid-step velocity), from z0 at the first sample."""
    vm = np.empty_like(v)
    vm[1:] = 0.5 * (v[1:] + v[:-1])
    vm[0] = v[0]
    x = np.abs(vm) * h / x_hys
    small = x < _SMALL_AH
    e = np.exp(-x)
    b = np.where(small, vm * h * (1.0 - 0.5 * x), np.sign(vm) * x_hys * -np.expm1(-np.where(small, 1.0, x)))
    e = np.where(small, 1.0 - x, e)
    e[0], b[0] = 0.0, z0
    return _exp_scan(e[None, :], b[None, :])[0]


def hys_columns(v: np.ndarray, h: float, nw: int, x_hys: float) -> tuple[np.ndarray, np.ndarray]:
    """(z_h where v ≥ 0, else 0; z_h where v < 0, else 0) over a window whose first ``nw``
    samples are a whole warm-up cycle: z_h starts in the periodic state of that cycle (the
    fixed point of its affine map z ← E·z + B), so no start-up transient reaches the fit."""
    if nw > 1:
        B = hys_state(v[:nw + 1], h, x_hys, 0.0)[-1]
        E = hys_state(v[:nw + 1], h, x_hys, 1.0)[-1] - B
        z0 = B / (1.0 - E) if E < 1.0 - 1e-12 else 0.0
    else:
        z0 = 0.0
    zh = hys_state(v, h, x_hys, z0)
    pos = v >= 0.0
    return np.where(pos, zh, 0.0), np.where(pos, 0.0, zh)




def _window_record(windows: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]],
                   X: np.ndarray | None = None) -> _Record:
    """Concatenate (v, F, h, n_warm) windows into one record with state resets;
    ``X``: linear terms at the fit samples (see :class:`_Record`)."""
    vs_, hs, Fs_, fit, reset = [], [], [], [], []
    off = 0
    for v, F, h, nw in windows:
        reset.append(off)
        fit.append(np.arange(off + nw, off + v.size))
        vs_.append(v)
        hs.append(h)
        Fs_.append(F[nw:])
        off += v.size
    return _Record(np.concatenate(vs_), np.concatenate(hs), np.asarray(reset), np.concatenate(fit),
                   np.concatenate(Fs_), X)

