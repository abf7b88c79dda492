"""LuGre parameter set of the RD-1097-01 and its current-dependent laws (6)–(11).

Pure numerics: no I/O here (loading a parameters *file* is in
:mod:`mrctl.config`). Every method takes and returns plain floats because
these run on the 1 kHz hot path, where numpy scalars cost microseconds.
Units are SI: m, m/s, N, A, s.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Final

# Below this |x| = |I/Bc| the Langevin function is evaluated by its Taylor
# series: coth(x) - 1/x cancels catastrophically for small x, and is 0/0 at 0.
_LANGEVIN_SERIES_BELOW: Final = 0.05


def langevin(x: float) -> float:
    """L(x) = coth(x) - 1/x, exact and finite at and near 0 (L(0) = 0)."""
    if -_LANGEVIN_SERIES_BELOW < x < _LANGEVIN_SERIES_BELOW:
        x2 = x * x
        # x/3 - x^3/45 + 2x^5/945 - x^7/4725; next term ~2e-17 at |x| = 0.05
        return x * (1.0 / 3.0 + x2 * (-1.0 / 45.0 + x2 * (2.0 / 945.0 - x2 / 4725.0)))
    return 1.0 / math.tanh(x) - 1.0 / x


@dataclass(frozen=True, slots=True)
class LuGreParams:
    """Table I's thirteen constants and three bench terms (SI units).

    The first thirteen are the paper's Table I (names as in the spec),
    identified for 0 … 0.55 A under a 2 Hz sine. ``sigma1`` is negative below
    ~0.26 A: the fit is not physical there, and the model keeps it because
    the paper's inverse law assumes it.

    The last three are what real benches add around the damper's friction
    (docs/identification.md); their defaults (0) leave Table I unchanged:

    - ``F_offset`` (N): a constant force: a gas accumulator's preload, a
      load cell's zero;
    - ``k_x`` (N/m): a linear stiffness on displacement (the accumulator);
    - ``tau_input`` (s): a first-order lag between the commanded input and
      the input the damper feels (coil inductance, driver).

    The damper's force is then F = F_LuGre(z, v, I_d) + F_offset + k_x·x,
    where I_d follows the command with time constant ``tau_input``.
    """

    F0: float = 2.90  # N, residual Coulomb force at 0 A
    Ac: float = 63.234  # N
    Bc: float = -0.176  # A
    sigma0A: float = 1.396e5  # N/(A·m)
    sigma0B: float = 8.96e4  # N/m
    sigma1A: float = 1.127e3  # N·s/(A·m)
    sigma1B: float = -289.1  # N·s/m
    sigma2A: float = 99.52  # N·s/(A·m)
    sigma2B: float = 14.55  # N·s/m
    FsA: float = 13.8  # N/A
    FsB: float = 0.6466  # N
    vsA: float = -0.0164  # m/(s·A)
    vsB: float = 0.0281  # m/s
    F_offset: float = 0.0  # N, constant force (accumulator preload, load-cell zero)
    k_x: float = 0.0  # N/m, stiffness on displacement
    tau_input: float = 0.0  # s, first-order lag of the input the damper feels

    def __reduce__(self) -> tuple[type[LuGreParams], tuple[float, ...]]:
        """Pickled by value: the compiled build's frozen class cannot be
        rebuilt field by field, and the reload child and sweep workers send
        parameter sets across processes."""
        return (LuGreParams, tuple([getattr(self, f.name) for f in fields(self)]))

    # -- laws (6)–(11) -----------------------------------------------------
    def Fc(self, I: float) -> float:
        """Coulomb force (N), eq (6): a squared Langevin function of I/Bc."""
        if self.Bc == 0.0:  # degenerate fit: L(±inf)² = 1 for I != 0
            return self.F0 if I == 0.0 else self.Ac + self.F0
        L = langevin(I / self.Bc)
        return self.Ac * L * L + self.F0

    def sigma0(self, I: float) -> float:
        """Bristle stiffness (N/m), eq (7)."""
        return self.sigma0A * I + self.sigma0B

    def sigma1(self, I: float) -> float:
        """Bristle damping (N·s/m), eq (8)."""
        return self.sigma1A * I + self.sigma1B

    def sigma2(self, I: float) -> float:
        """Viscous coefficient (N·s/m), eq (9)."""
        return self.sigma2A * I + self.sigma2B

    def Fs(self, I: float) -> float:
        """Stiction force (N), eq (10)."""
        return self.FsA * I + self.FsB

    def vs(self, I: float) -> float:
        """Stribeck velocity (m/s), eq (11)."""
        return self.vsA * I + self.vsB

    def bench_force(self, x: float) -> float:
        """The force around the friction (N): F_offset + k_x·x."""
        return self.F_offset + self.k_x * x

    def g(self, v: float, I: float, Fc: float | None = None) -> float:
        """Stribeck function g(v, I) (N), eq (3); ``Fc`` may be given (eq 12 lags it)."""
        if Fc is None:
            Fc = self.Fc(I)
        r = v / self.vs(I)
        return Fc + (self.Fs(I) - Fc) * math.exp(-r * r)

    # -- bookkeeping ---------------------------------------------------------
    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    def with_overrides(self, **overrides: float) -> "LuGreParams":
        return replace(self, **overrides)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """Table I's thirteen names (the spec's), in its order."""
        return tuple(f.name for f in fields(cls))[:13]

    @classmethod
    def bench_names(cls) -> tuple[str, ...]:
        """The bench terms around the friction: F_offset, k_x, tau_input."""
        return tuple(f.name for f in fields(cls))[13:]

    @classmethod
    def all_names(cls) -> tuple[str, ...]:
        """Every name a parameters file may set."""
        return tuple(f.name for f in fields(cls))

    def check_range(self, I_max: float, samples: int = 201, I_min: float = 0.0, unit: str = "A") -> list[str]:
        """Problems that make the model meaningless on [I_min, I_max] (empty if fine).

        The state equation divides by g, whose minimum over v is min(Fc, Fs),
        and needs vs != 0 and sigma0 > 0 for z to stay bounded. Checked on a
        grid, which is exact for the linear laws and ample for eq (6). A set
        identified from a driver's command voltage has laws in volts: pass its
        fitted input range and ``unit="V"``."""
        problems: list[str] = []
        if not self.tau_input >= 0.0:
            problems.append(f"tau_input must be >= 0 s, got {self.tau_input:g}")
        span = I_max - I_min
        for name, fn in (("sigma0", self.sigma0), ("Fs", self.Fs), ("vs", self.vs), ("Fc", self.Fc)):
            worst = min(fn(I_min + span * k / (samples - 1)) for k in range(samples))
            if not worst > 0.0:
                problems.append(
                    f"{name}(I) must stay > 0 for I in [{I_min:g}, {I_max:g}] {unit}, but reaches {worst:.6g}"
                )
        return problems


TABLE_I = LuGreParams()


def params_from_mapping(data: Any) -> LuGreParams:
    """Build a parameter set from a mapping of spec names, Table I filling gaps.

    Raises ``ValueError`` naming the offending key; the config layer turns it
    into a user-facing error with the file and key path."""
    if not isinstance(data, dict):
        raise ValueError(f"parameters must be a mapping of {', '.join(LuGreParams.all_names())}")
    known = set(LuGreParams.all_names())
    values: dict[str, float] = {}
    for key, value in data.items():
        if key not in known:
            raise ValueError(f"{key}: unknown parameter (expected one of {', '.join(LuGreParams.all_names())})")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{key}: must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ValueError(f"{key}: must be finite, got {value!r}")
        values[key] = float(value)
    return TABLE_I.with_overrides(**values)
