#!/usr/bin/env python3
"""Inverse-law study: the paper law vs the smooth law, and what each part does.

Runs the paper's Fig 5 scenario (10 mm / 1 Hz sine, I_max = 0.6 A, 4 s,
no driver lag) for c_des in {100, 250, 500, 1000} N·s/m with:

- ``paper``: eq (12) as published;
- ``smooth``: the shipped defaults (ε = 3 N/A, slew 50 A/s);
- ablations: slew bound only (ε = 0), regularisation only (no slew bound),
  tighter/looser ε and slew, and two rejected designs kept here as study
  code: ``full-root`` (solve eq 1 for I with every parameter at the new
  current, clip to the reachable force range) and ``implicit-zdot`` (smooth
  law with ż evaluated at the new current by fixed-point passes).

Prints markdown tables; ``--write-docs`` rewrites the generated section of
docs/inverse-laws.md. Figures are deterministic (no timing involved).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_yaml, validate_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.laws.base import Measurement  # noqa: E402
from mrctl.laws.inverse import SmoothInverse, _ModelBasedLaw  # noqa: E402
from mrctl.model.lugre import force  # noqa: E402
from mrctl.offline.simulate import simulate  # noqa: E402
from mrctl.util.gendoc import replace_block  # noqa: E402

C_VALUES = (100.0, 250.0, 500.0, 1000.0)
EXP = ROOT / "config" / "experiments"


class FullRoot(_ModelBasedLaw):
    """Rejected design: I with F(I; z, v) = F_des using all current dependence."""

    name = "full-root"

    def current(self, m: Measurement, F_des: float) -> float:
        v = m.v
        z = self._advance(v)
        p = self.p

        def f(I: float) -> float:
            return force(p, z, v, I) - F_des

        lo, hi = 0.0, self.I_max
        flo, fhi = f(lo), f(hi)
        if flo * fhi > 0.0:
            I = lo if abs(flo) < abs(fhi) else hi
        else:
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                fm = f(mid)
                if (fm > 0.0) == (flo > 0.0):
                    lo, flo = mid, fm
                else:
                    hi = mid
            I = 0.5 * (lo + hi)
        self.I_prev = I
        return I


class ImplicitZdot(SmoothInverse):
    """Rejected design: smooth law with ż at the new current (2 fixed-point passes)."""

    name = "implicit-zdot"

    def current(self, m: Measurement, F_des: float) -> float:
        v = m.v
        p = self.p
        Ip = self.I_prev
        z = self._advance(v)
        I = Ip
        for _ in range(3):
            zdot = self.model.zdot(v, I)
            B = p.sigma0B * z + p.sigma1B * zdot + p.sigma2B * v
            D = p.sigma0A * z + p.sigma1A * zdot + p.sigma2A * v
            In = (D * (F_des - B) + self.eps2 * Ip) / (D * D + self.eps2)
            In = min(max(In, Ip - self.max_step_A), Ip + self.max_step_A)
            I = min(max(In, 0.0), self.I_max) if In == In else 0.0
        self.I_prev = I
        return I


def run(c_des: float, law: str = "paper", make=None, **inverse) -> dict[str, float]:
    data = load_yaml(EXP / ("fig5_paper.yaml" if law == "paper" else "fig5.yaml"))
    data["demand"]["c_des"] = c_des
    if law != "paper":
        data["inverse"] = {"law": "smooth", **inverse}
    exp = build(validate_experiment(data, EXP))
    if make is not None:
        exp.law = make(exp)
    res = simulate(exp, 4.0)
    if res.fault is not None:  # a table of NaN is no measurement
        raise SystemExit(f"c_des {c_des:g}, {exp.law.name}: {res.fault}")
    return res.summary


def _row(label: str, results: list[dict[str, float]]) -> str:
    cells = [f"{100 * r['force_nrmse']:.3f} % / {r['max_current_step_A']:.3f} A" for r in results]
    return f"| {label} | " + " | ".join(cells) + " |"


def tables() -> str:
    out: list[str] = []
    head = "| law | " + " | ".join(f"c_des = {c:g}" for c in C_VALUES) + " |"
    sep = "|---|" + "---|" * len(C_VALUES)
    paper = [run(c) for c in C_VALUES]
    smooth = [run(c, "smooth") for c in C_VALUES]
    out.append("### Shipped laws: force NRMSE / largest current step after the first period\n")
    out += [head, sep, _row("`paper` (eq 12)", paper), _row("`smooth` (ε = 3 N/A, 50 A/s)", smooth)]
    out.append("")
    out.append("### Shares of ticks at the current limits (after the first period)\n")
    out.append("| law | " + " | ".join(f"c_des = {c:g}: at 0 A / at I_max" for c in C_VALUES) + " |")
    out.append(sep)
    for label, res in (("`paper`", paper), ("`smooth`", smooth)):
        out.append(f"| {label} | " + " | ".join(
            f"{100 * r['share_at_zero']:.1f} % / {100 * r['share_at_I_max']:.1f} %" for r in res) + " |")
    out.append("")
    verdict = all(s["force_nrmse"] <= p["force_nrmse"] and s["max_current_step_A"] <= 0.05 + 1e-12
                  for s, p in zip(smooth, paper))
    out.append(f"Smooth law meets both targets (step ≤ 0.05 A, NRMSE ≤ paper) at every c_des: **{'yes' if verdict else 'NO'}**.\n")
    out.append("### Ablation and rejected designs (same scenario; NRMSE / largest step)\n")
    out += [head, sep]
    variants = [
        ("slew bound only (ε = 0, 50 A/s)", dict(eps_N_per_A=0.0)),
        ("regularisation only (ε = 3, no slew bound)", dict(max_slew_A_per_s=1e6)),
        ("ε = 1 N/A, 50 A/s", dict(eps_N_per_A=1.0)),
        ("ε = 5 N/A, 50 A/s", dict(eps_N_per_A=5.0)),
        ("ε = 3 N/A, 40 A/s", dict(max_slew_A_per_s=40.0)),
        ("ε = 10 N/A, no slew bound", dict(eps_N_per_A=10.0, max_slew_A_per_s=1e6)),
    ]
    for label, kw in variants:
        out.append(_row(label, [run(c, "smooth", **kw) for c in C_VALUES]))
    full = [run(c, "smooth", make=lambda e: FullRoot(e.params, e.I_max, e.dt)) for c in C_VALUES]
    out.append(_row("rejected: full-model root (all parameters at new I)", full))
    imp = [run(c, "smooth", make=lambda e: ImplicitZdot(e.params, e.I_max, e.dt)) for c in C_VALUES]
    out.append(_row("rejected: smooth with ż at the new current", imp))
    return "\n".join(out) + "\n"


BEGIN, END = "<!-- BEGIN GENERATED: bench/inverse_laws.py -->", "<!-- END GENERATED -->"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write-docs", action="store_true", help="update docs/inverse-laws.md")
    args = ap.parse_args()
    text = tables()
    print(text)
    if args.write_docs:
        doc = ROOT / "docs" / "inverse-laws.md"
        replace_block(doc, BEGIN, END, text.rstrip("\n"))  # the table ends in a newline
        print(f"updated {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
