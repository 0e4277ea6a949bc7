"""`make replicate`: the paper's Table 1 (materials A and B) side by side with our fit.

Runs examples/paper-material-a.json and -b.json in-process (FEM reference, then the annealing
with the spec's chains), and prints k, d, depth and the mean nodal discrepancy per force and on
average, beside the paper's values (Choi et al. 2004, Table 1 and Sec. 4.4).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import fpm
from fpm.calibration import calibrate

ROOT = Path(__file__).resolve().parents[1]
PAPER = {
    "A": {"k": 38.60, "d": 20.36, "depth": 10},
    "B": {"k": 358.6, "d": 313.6, "depth": 10},
}
PAPER_DISCREPANCY = "1.4% at the smallest force, about 9% on average"


def run(material: str) -> tuple[fpm.Problem, object, float]:
    problem = fpm.load_problem(ROOT / "examples" / f"paper-material-{material.lower()}.json")
    t0 = time.perf_counter()
    reference = fpm.solve_fem(problem)
    result = calibrate(problem, reference=reference)
    return problem, result, time.perf_counter() - t0


def main() -> None:
    results = {}
    for m in ("A", "B"):
        print(f"calibrating material {m} ...", file=sys.stderr, flush=True)
        results[m] = run(m)
    print(f"\n{'':<26}{'material A':>14}{'paper A':>10}{'material B':>14}{'paper B':>10}")
    for key, unit in (("k", "N/m"), ("d", "N s/m"), ("depth", "layers")):
        row = f"{key + ' (' + unit + ')':<26}"
        for m in ("A", "B"):
            row += f"{getattr(results[m][1], key):>14.4g}{PAPER[m][key]:>10.4g}"
        print(row)
    pa, ra, _ = results["A"]
    pb, rb, _ = results["B"]
    for i in range(len(pa.load_cases)):
        label = f"discrepancy {pa.load_cases[i].name} / {pb.load_cases[i].name}"
        paper = "1.4" if i == 0 else "-"
        print(
            f"{label:<26}{ra.discrepancy[i]:>13.3f}%{paper:>10}{rb.discrepancy[i]:>13.3f}%{paper:>10}"
        )
    print(f"{'discrepancy, mean':<26}{ra.mean_discrepancy:>13.3f}%{'~9':>10}"
          f"{rb.mean_discrepancy:>13.3f}%{'~9':>10}")  # fmt: skip
    print(f"{'settle steps (per force)':<26}{str(ra.settle_steps):>24}{str(rb.settle_steps):>24}")
    print(f"{'all load cases settled':<26}{str(ra.settled):>14}{'':>10}{str(rb.settled):>14}")
    print(f"{'wall time (s)':<26}{results['A'][2]:>14.1f}{'':>10}{results['B'][2]:>14.1f}")
    ratio = rb.k / ra.k
    print(f"\nk_B / k_A = {ratio:.4f} (E_B / E_A = 10; {abs(ratio / 10 - 1) * 100:.2f}% off; "
          f"paper: {PAPER['B']['k'] / PAPER['A']['k']:.4f})")  # fmt: skip
    print(f"discrepancies in % of h (h = {pa.h * 1e3:.4f} mm); paper: {PAPER_DISCREPANCY}")
    goals = {
        "smallest force <= 1.0% of h": max(ra.discrepancy[0], rb.discrepancy[0]) <= 1.0,
        "mean over forces <= 2.5% of h": max(ra.mean_discrepancy, rb.mean_discrepancy) <= 2.5,
        "k_B / k_A = 10 within 1%": abs(ratio / 10 - 1) <= 0.01,
        "every load case settled": ra.settled and rb.settled,
    }
    for goal, met in goals.items():
        print(f"  [{'met' if met else 'NOT MET'}] {goal}")


if __name__ == "__main__":
    main()
