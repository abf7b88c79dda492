"""Never an absurd parameter set: what the data can support, and the final check.

:class:`Support` derives, from the measured record, the range each LuGre
quantity may take: the optimisers are bounded by it, and
:func:`check_laws` evaluates every law of a fitted set on a fine grid of
the fitted input range and refuses the set (IdentificationError: no YAML is
written) if any leaves it, naming the law, the input where it fails and
what to try. The limits, relative to the force amplitude F_amp (half the
1–99.5 % range of the measured force), the velocity scale v_max (99.5th
percentile of |v|) and the stroke amplitude x_amp:

- σ0, Fs, vs, Fc > 0 and σ2 ≥ 0 everywhere (g ≥ min(Fc, Fs) > 0 follows);
- Fc ≥ 1 % of F_amp: a Coulomb force below that is not seen in the data
  (the damper hardly slid: a stroke too short for the force to saturate);
- Fc, Fs ≤ 3·F_amp: a force the record never came near;
- vs within [0.1 %, 1000 %] of v_max: a Stribeck velocity below the
  velocity resolution makes Fs a spike at v = 0 that no sample measures;
- σ0 ≤ F_amp / (10⁻⁶·x_amp): a pre-sliding length below a millionth of the stroke.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.offline.identify.errors import IdentificationError

__all__ = ["Support", "check_laws", "law_problems", "theta_problems"]

_GRID = 401
FC_MIN_REL = 0.01
F_MAX_REL = 3.0
VS_MIN_REL = 1e-3
VS_MAX_REL = 10.0
LAMBDA_MIN_REL = 1e-6


@dataclass(frozen=True)
class Support:
    """The scales of a record that bound what a fit may claim."""

    F_amp: float  # N
    v_max: float  # m/s
    x_amp: float | None  # m (None: no displacement recorded)

    @classmethod
    def of(cls, F: np.ndarray, v: np.ndarray, x: np.ndarray | None = None) -> "Support":
        lo, hi = np.percentile(F, [1.0, 99.5]) if F.size else (0.0, 0.0)
        F_amp = max(0.5 * float(hi - lo), 1e-9)
        v_max = max(float(np.percentile(np.abs(v), 99.5)) if v.size else 0.0, 1e-12)
        x_amp = None
        if x is not None and x.size:
            xl, xh = np.percentile(x, [0.5, 99.5])
            x_amp = max(0.5 * float(xh - xl), 1e-12)
        return cls(F_amp, v_max, x_amp)

    # Bounds for the optimisers: wider than the limits, so that a fit the
    # data push past a limit is refused (check_laws), not silently clipped.
    def force_bounds(self) -> tuple[float, float]:
        return FC_MIN_REL * self.F_amp * 0.1, 1.5 * F_MAX_REL * self.F_amp

    def vs_bounds(self) -> tuple[float, float]:
        return 0.5 * VS_MIN_REL * self.v_max, 1.5 * VS_MAX_REL * self.v_max

    def sigma0_max(self) -> float:
        """The largest σ0 the data support (the limit; optimisers get 1.5 × it)."""
        x = self.x_amp if self.x_amp is not None else self.v_max
        return self.F_amp / (LAMBDA_MIN_REL * x)

    def floors(self) -> dict[str, float]:
        """The least value each law may take (bounded law fits, :func:`fit_laws`)."""
        return {"sigma0": 1e-9 * self.sigma0_max(), "sigma2": 0.0, "Fs": FC_MIN_REL * self.F_amp * 0.1,
                "vs": VS_MIN_REL * self.v_max, "Fc": FC_MIN_REL * self.F_amp}


def theta_problems(theta: dict[str, float], sup: Support, where: str) -> list[str]:
    """Every way one level's Θ leaves what its data support (the same limits as the laws)."""
    p = LuGreParams(F0=theta["Fc"], Ac=0.0, Bc=-1.0, sigma0A=0.0, sigma0B=theta["sigma0"], sigma1A=0.0,
                    sigma1B=theta["sigma1"], sigma2A=0.0, sigma2B=theta["sigma2"], FsA=0.0, FsB=theta["Fs"],
                    vsA=0.0, vsB=theta["vs"])
    out = []
    for msg in law_problems(p, 0.0, 0.0, sup, scope="level"):
        name, rest = msg.split("(", 1)
        text = rest.split(") = ", 1)[1].split(" (law over", 1)[0]
        advice = msg.split("; try: ", 1)[1]
        out.append(f"{where}: {name} = {text}; try: {advice}")
    return out


def _advice(name: str, what: str, scope: str = "law") -> str:
    if scope == "level" and what in ("negative", "high"):
        return ("the model cannot describe this level's force: fit the force offset and stiffness if they are off "
                "(a dataset's model.offset/model.stiffness; mrctl identify fits them unless --no-offset), check "
                "the force and displacement columns' scales, and leave out what the model cannot describe (rest, "
                "ramps, run-away: a dataset's use:/exclude: windows)")
    if name in ("Fs", "vs") and what in ("high", "low"):
        return ("the Stribeck peak is not determined by the data: fit only steady motion (exclude rest, "
                "pauses and ramps with use:/exclude: windows), and check the velocity column's scale")
    if name == "Fc" and what == "low":
        return ("the damper hardly slides in this record: use a longer stroke or a lower frequency, and check "
                "the force column's scale and offset")
    if what == "negative":
        return ("the law is extrapolated past what the levels support: add input levels across the range, drop "
                "an outlying level, or narrow the input range")
    return "check the columns' scales; exclude parts of the record the model cannot describe (rest, ramps, run-away)"


def law_problems(p: LuGreParams, u_lo: float, u_hi: float, sup: Support, unit: str = "A",
                 scope: str = "law") -> list[str]:
    """Every way the laws of ``p`` leave the physical/supported range on [u_lo, u_hi]."""
    u = np.linspace(u_lo, u_hi, _GRID)
    vals = {name: np.array([getattr(p, name)(float(q)) for q in u])  # paper or table laws
            for name in ("sigma0", "sigma2", "Fs", "vs", "Fc")}
    out = []

    def where(mask: np.ndarray, arr: np.ndarray, worst_low: bool) -> tuple[float, float]:
        k = int(np.argmin(arr) if worst_low else np.argmax(arr))
        return float(u[k]), float(arr[k])

    lo_F, hi_F = FC_MIN_REL * sup.F_amp, F_MAX_REL * sup.F_amp
    vs_lo, vs_hi = VS_MIN_REL * sup.v_max, VS_MAX_REL * sup.v_max
    # the hysteretic stiffness saturates at k_hys·x_hys: a friction of its own (a seal's, field-free), which the
    # damper's least sliding force includes beside Fc
    F_h = min(p.k_hys_pos, p.k_hys_neg) * p.x_hys if p.has_hysteresis else 0.0
    F_h = F_h if F_h > 0.0 else 0.0
    rules = [
        ("sigma0", "N/m", lambda a: a <= 0.0, True, "negative", "must stay > 0"),
        ("Fs", "N", lambda a: a <= 0.0, True, "negative", "must stay > 0"),
        ("vs", "m/s", lambda a: a <= 0.0, True, "negative", "must stay > 0"),
        ("Fc", "N", lambda a: a <= 0.0, True, "negative", "must stay > 0"),
        ("sigma2", "N·s/m", lambda a: a < 0.0, True, "negative", "must stay >= 0 (viscous damping)"),
        ("Fc", "N", lambda a: (a > 0.0) & (a + F_h < lo_F), True, "low",
         f"is below {lo_F:.3g} N, 1 % of the force amplitude {sup.F_amp:.3g} N"
         + (f", with the hysteretic stiffness's {F_h:.3g} N" if F_h else "")),
        ("Fc", "N", lambda a: a > hi_F, False, "high",
         f"exceeds {hi_F:.3g} N, 3 × the force amplitude {sup.F_amp:.3g} N"),
        ("Fs", "N", lambda a: a > hi_F, False, "high",
         f"exceeds {hi_F:.3g} N, 3 × the force amplitude {sup.F_amp:.3g} N"),
        ("vs", "m/s", lambda a: (a > 0.0) & (a < vs_lo), True, "low",
         f"is below {vs_lo:.3g} m/s, 0.1 % of the velocity scale {sup.v_max:.3g} m/s"),
        ("vs", "m/s", lambda a: a > vs_hi, False, "high",
         f"exceeds {vs_hi:.3g} m/s, 10 × the velocity scale {sup.v_max:.3g} m/s"),
        ("sigma0", "N/m", lambda a: a > sup.sigma0_max(), False, "high",
         f"exceeds {sup.sigma0_max():.3g} N/m (a pre-sliding length below 1e-6 of the stroke)"),
    ]
    seen = set()
    for name, unit_q, bad, low, what, text in rules:
        arr = vals[name]
        mask = bad(arr)
        if name in seen or not np.any(mask):
            continue
        seen.add(name)
        uu, val = where(mask, np.where(mask, arr, np.inf if low else -np.inf), low)
        out.append(f"{name}({uu:.4g} {unit}) = {val:.4g} {unit_q} {text} (law over the fitted input range "
                   f"[{u_lo:.4g}, {u_hi:.4g}] {unit}); try: {_advice(name, what, scope)}")
    if not (math.isfinite(p.tau_input) and p.tau_input >= 0.0):
        out.append(f"tau_input = {p.tau_input:g} s must be >= 0")
    if p.has_hysteresis and not (p.x_hys > 0.0 and max(abs(p.k_hys_pos), abs(p.k_hys_neg)) * p.x_hys <= hi_F):
        out.append(f"the hysteretic stiffness's force k_hys·x_hys = {max(abs(p.k_hys_pos), abs(p.k_hys_neg)) * p.x_hys:.4g} "
                   f"N exceeds {hi_F:.3g} N, 3 × the force amplitude (x_hys = {p.x_hys:.4g} m); try: "
                   f"{_advice('k_hys', 'high', scope)}")
    return out


def check_laws(p: LuGreParams, u_lo: float, u_hi: float, sup: Support, unit: str = "A") -> None:
    """IdentificationError listing every law that leaves the physical/supported range."""
    problems = law_problems(p, u_lo, u_hi, sup, unit)
    if problems:
        head = "the fitted parameter set is not physical, so no parameters file was written"
        raise IdentificationError(head + ":\n  " + "\n  ".join(problems))
