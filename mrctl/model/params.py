"""LuGre parameter set of the RD-1097-01 and its current-dependent laws (6)–(11).

Pure numerics: no I/O here (loading a parameters *file* is in
:mod:`mrctl.config`). Every method takes and returns plain floats because
these run on the 1 kHz hot path, where numpy scalars cost microseconds.
Units are SI: m, m/s, N, A, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
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


#: the per-level quantities a table law holds, in the order of :meth:`ThetaTable.at`
TABLE_NAMES: Final = ("Fc", "Fs", "sigma0", "sigma1", "sigma2", "vs")
#: optional per-level bench terms of a table (both or neither), after TABLE_NAMES
TABLE_BENCH_NAMES: Final = ("F_offset", "k_x")
#: optional per-level hysteretic stiffness of a table (both or neither, with the bench terms), after them
TABLE_HYS_NAMES: Final = ("k_hys_pos", "k_hys_neg")


@dataclass(frozen=True, slots=True)
class ThetaTable:
    """``laws: table``: Θ at identified input levels, interpolated piecewise linearly.

    Why: the paper's laws (6)–(11) have a fixed shape (a squared Langevin
    function, straight lines) that a real damper's per-level Θ need not
    follow; a table passes through every identified level. Piecewise linear
    interpolation is monotone (it never overshoots between levels, so a
    positive Θ at the levels stays positive) and, within a segment, affine in
    the input as the paper's linear laws are. Outside ``[u[0], u[-1]]`` the
    end values are held (no extrapolated, possibly negative, Θ).

    ``u``: the levels (A or V, strictly increasing, ≥ 2); ``values``: one
    tuple per name of :data:`TABLE_NAMES`, as long as ``u``, SI units, and
    optionally two more, :data:`TABLE_BENCH_NAMES`: the force offset (N) and
    stiffness (N/m) per level, which then replace the set's constant
    ``F_offset`` and ``k_x`` (a real bench's per-level fits differ in them),
    and after them optionally :data:`TABLE_HYS_NAMES`: the hysteretic
    stiffness per direction (N/m) per level, replacing ``k_hys_pos`` and
    ``k_hys_neg`` (the set's ``x_hys`` is its length).
    """

    u: tuple[float, ...]
    values: tuple[tuple[float, ...], ...]

    def __reduce__(self) -> tuple[type[ThetaTable], tuple[Any, ...]]:
        """Pickled by value (as :class:`LuGreParams`)."""
        return (ThetaTable, (self.u, self.values))

    def problems(self) -> list[str]:
        """What makes the table unusable (empty if fine): key paths under ``table``."""
        out: list[str] = []
        n = len(self.u)
        if n < 2:
            out.append(f"table.input: needs at least 2 levels, got {n}")
        for k in range(n):
            if not math.isfinite(self.u[k]):
                out.append(f"table.input[{k}]: must be finite, got {self.u[k]!r}")
        for k in range(1, n):
            if not self.u[k] > self.u[k - 1]:
                out.append(f"table.input: must be strictly increasing (monotone), but [{k - 1}] = "
                           f"{self.u[k - 1]:g} and [{k}] = {self.u[k]:g}")
                break
        names = TABLE_NAMES + TABLE_BENCH_NAMES + TABLE_HYS_NAMES
        if len(self.values) not in (6, 8, 10):
            out.append(f"table: needs {', '.join(TABLE_NAMES)} (and optionally both {', '.join(TABLE_BENCH_NAMES)}, "
                       f"then both {', '.join(TABLE_HYS_NAMES)})")
            return out
        for j in range(len(self.values)):
            name = names[j]
            col = self.values[j]
            if len(col) != n:
                out.append(f"table.{name}: {len(col)} values for {n} levels in table.input")
                continue
            for k in range(n):
                x = col[k]
                if not math.isfinite(x):
                    out.append(f"table.{name}[{k}]: must be finite, got {x!r}")
                elif j < 6 and name != "sigma1" and not x > 0.0:
                    out.append(f"table.{name}[{k}]: must be > 0, got {x:g}")
        return out

    def value(self, j: int, I: float) -> float:
        """Θ entry ``TABLE_NAMES[j]`` at input I, piecewise linear, ends held."""
        u = self.u
        col = self.values[j]
        n = len(u)
        if I <= u[0]:
            return col[0]
        if I >= u[n - 1]:
            return col[n - 1]
        k = 1
        while u[k] < I:
            k += 1
        if u[k] == I:  # at a level: its value exactly
            return col[k]
        u0 = u[k - 1]
        w = (I - u0) / (u[k] - u0)
        return col[k - 1] + (col[k] - col[k - 1]) * w

    def local(self, j: int, I: float) -> tuple[float, float]:
        """(A, B) of the segment the input I falls in, value = A·I + B there
        (the end segments beyond the levels): the inverse laws' ∂Θ/∂I, as the
        paper's linear laws give it."""
        u = self.u
        col = self.values[j]
        n = len(u)
        k = 1
        while k < n - 1 and u[k] < I:
            k += 1
        a = (col[k] - col[k - 1]) / (u[k] - u[k - 1])
        return a, col[k - 1] - a * u[k - 1]

    def has_bench(self) -> bool:
        """Whether the table holds the per-level F_offset and k_x."""
        return len(self.values) >= 8

    def has_hys(self) -> bool:
        """Whether the table holds the per-level hysteretic stiffness (k_hys_pos, k_hys_neg)."""
        return len(self.values) == 10

    def bench_force(self, I: float, x: float) -> float:
        """F_offset(I) + k_x(I)·x (N), the per-level bench terms interpolated."""
        return self.value(6, I) + self.value(7, I) * x

    def as_dict(self) -> dict[str, list[float]]:
        """The ``table:`` mapping of a parameters file."""
        out: dict[str, list[float]] = {"input": list(self.u)}
        names = TABLE_NAMES + TABLE_BENCH_NAMES + TABLE_HYS_NAMES
        for j in range(len(self.values)):
            out[names[j]] = list(self.values[j])
        return out


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

    Optional terms (docs/identification.md, "Model terms"), off at 0, where
    a set without them computes bit for bit what it did before:
    ``sigma1_vd`` (m/s), σ1(v) = σ1·exp(−(v/v_d)²) (Canudas de Wit 1995);
    ``tau_input_fall`` (s), the input lag while the input falls (a driver
    that forces the current up and lets it decay through the coil);
    ``k_hys_pos``, ``k_hys_neg`` (N/m), ``x_hys`` (m), a hysteretic (Dahl)
    stiffness: ż_h = v − |v|·z_h/x_hys, force k_hys·z_h, k_hys by the sign
    of v (≥ 0: pos): a force growing with the distance since the last
    reversal, unlike in the two directions (accumulator, valves);
    ``tau_field`` (s), the damper's own lag from its coil current to the
    field (eddy currents in the housing), after the driver's ``tau_input``.

    ``table`` (None by default: the paper's laws) replaces laws (6)–(11) by
    a :class:`ThetaTable` (``laws: table`` in a parameters file); the thirteen
    constants are then still the paper-law fit of the same levels, which the
    inverse laws' ∂F/∂I uses.
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
    sigma1_vd: float = 0.0  # m/s, sigma1(v) = sigma1·exp(-(v/vd)²); 0: off (sigma1 constant)
    tau_input_fall: float = 0.0  # s, the input lag while the input falls; 0: tau_input (symmetric)
    k_hys_pos: float = 0.0  # N/m, hysteretic (Dahl) stiffness while v >= 0
    k_hys_neg: float = 0.0  # N/m, ... while v < 0
    x_hys: float = 0.0  # m, its saturation length (z_h -> ±x_hys); > 0 when either stiffness is
    tau_field: float = 0.0  # s, the damper's own lag from its current to the field, after tau_input's; 0: none
    table: ThetaTable | None = None  # laws: table (None: the paper's laws 6-11)

    def __reduce__(self) -> tuple[type[LuGreParams], tuple[Any, ...]]:
        """Pickled by value: the compiled build's frozen class cannot be
        rebuilt field by field, and the reload child and sweep workers send
        parameter sets across processes."""
        return (LuGreParams, tuple([getattr(self, f.name) for f in fields(self)]))

    # -- laws (6)–(11) -----------------------------------------------------
    @property
    def laws(self) -> str:
        """``"paper"`` (laws 6–11) or ``"table"``."""
        return "paper" if self.table is None else "table"

    def Fc(self, I: float) -> float:
        """Coulomb force (N), eq (6): a squared Langevin function of I/Bc."""
        if self.table is not None:
            return self.table.value(0, I)
        if self.Bc == 0.0:  # degenerate fit: L(±inf)² = 1 for I != 0
            return self.F0 if I == 0.0 else self.Ac + self.F0
        L = langevin(I / self.Bc)
        return self.Ac * L * L + self.F0

    def sigma0(self, I: float) -> float:
        """Bristle stiffness (N/m), eq (7)."""
        if self.table is not None:
            return self.table.value(2, I)
        return self.sigma0A * I + self.sigma0B

    def sigma1(self, I: float) -> float:
        """Bristle damping (N·s/m), eq (8)."""
        if self.table is not None:
            return self.table.value(3, I)
        return self.sigma1A * I + self.sigma1B

    def sigma2(self, I: float) -> float:
        """Viscous coefficient (N·s/m), eq (9)."""
        if self.table is not None:
            return self.table.value(4, I)
        return self.sigma2A * I + self.sigma2B

    def Fs(self, I: float) -> float:
        """Stiction force (N), eq (10)."""
        if self.table is not None:
            return self.table.value(1, I)
        return self.FsA * I + self.FsB

    def vs(self, I: float) -> float:
        """Stribeck velocity (m/s), eq (11)."""
        if self.table is not None:
            return self.table.value(5, I)
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
    @property
    def has_hysteresis(self) -> bool:
        """Whether the hysteretic (Dahl) stiffness is on (its constants, or a table's per-level values)."""
        return self.k_hys_pos != 0.0 or self.k_hys_neg != 0.0 or (self.table is not None and self.table.has_hys())

    def tau_fall(self) -> float:
        """The input lag while the input falls (s): ``tau_input_fall``, or ``tau_input`` when 0."""
        return self.tau_input_fall if self.tau_input_fall > 0.0 else self.tau_input

    def extras(self) -> dict[str, float]:
        """The optional model terms that are on (non-zero), by name."""
        return {n: getattr(self, n) for n in self.extra_names() if getattr(self, n) != 0.0}

    def as_dict(self) -> dict[str, Any]:
        """The sixteen constants by name, the optional terms that are on; with a
        table also ``laws`` and ``table`` (what :func:`params_from_mapping`
        and a parameters file read back). A set without the optional terms
        gives exactly the sixteen keys it always has."""
        out: dict[str, Any] = {}
        for f in fields(self)[:16]:
            out[f.name] = getattr(self, f.name)
        out.update(self.extras())
        if self.table is not None:
            out["laws"] = "table"
            out["table"] = self.table.as_dict()
        return out

    def with_overrides(self, **overrides: float) -> "LuGreParams":
        kw: dict[str, Any] = dict(overrides)  # the numbers; the table is kept
        return replace(self, **kw)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """Table I's thirteen names (the spec's), in its order."""
        return tuple(f.name for f in fields(cls))[:13]

    @classmethod
    def bench_names(cls) -> tuple[str, ...]:
        """The bench terms around the friction: F_offset, k_x, tau_input."""
        return tuple(f.name for f in fields(cls))[13:16]

    @classmethod
    def extra_names(cls) -> tuple[str, ...]:
        """The optional model terms: sigma1_vd, tau_input_fall, k_hys_pos, k_hys_neg, x_hys, tau_field."""
        return tuple(f.name for f in fields(cls))[16:22]

    @classmethod
    def all_names(cls) -> tuple[str, ...]:
        """Every number a parameters file may set (``laws``/``table`` aside)."""
        return tuple(f.name for f in fields(cls))[:22]

    def check_range(self, I_max: float, samples: int = 201, I_min: float = 0.0, unit: str = "A") -> list[str]:
        """Problems that make the model meaningless on [I_min, I_max] (empty if fine).

        The state equation divides by g, whose minimum over v is min(Fc, Fs),
        and needs vs != 0 and sigma0 > 0 for z to stay bounded. Checked on a
        grid, which is exact for the linear laws and ample for eq (6). A set
        identified from a driver's command voltage has laws in volts: pass its
        fitted input range and ``unit="V"``."""
        problems: list[str] = []
        if self.table is not None:
            problems.extend(self.table.problems())
            if problems:
                return problems
        if not self.tau_input >= 0.0:
            problems.append(f"tau_input must be >= 0 s, got {self.tau_input:g}")
        problems.extend(extra_problems(self))
        span = I_max - I_min
        for name, fn in (("sigma0", self.sigma0), ("Fs", self.Fs), ("vs", self.vs), ("Fc", self.Fc)):
            worst = min(fn(I_min + span * k / (samples - 1)) for k in range(samples))
            if not worst > 0.0:
                problems.append(
                    f"{name}(I) must stay > 0 for I in [{I_min:g}, {I_max:g}] {unit}, but reaches {worst:.6g}"
                )
        return problems


TABLE_I = LuGreParams()


def extra_problems(p: LuGreParams) -> list[str]:
    """What makes the optional terms meaningless (empty if fine), each naming its key."""
    out: list[str] = []
    for name, what in (("sigma1_vd", "m/s"), ("tau_input_fall", "s"), ("x_hys", "m"), ("tau_field", "s")):
        if not getattr(p, name) >= 0.0:
            out.append(f"{name}: must be >= 0 {what} (0: off), got {getattr(p, name):g}")
    if p.has_hysteresis and not p.x_hys > 0.0:  # the constants or a table's columns
        out.append(f"x_hys: must be > 0 m when k_hys_pos or k_hys_neg is set (the hysteretic stiffness "
                   f"saturates at k_hys·x_hys), got {p.x_hys:g}")
    return out
