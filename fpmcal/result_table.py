"""The calibration result as the table ``fpmcal calibrate`` prints."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fpm.fitting.result import CalibrationResult


def result_table(problem: Any, result: CalibrationResult) -> str:
    """The calibration result as a readable table: the verdict first, the parameters, then per
    case the relative discrepancy beside % of h and the load compliance ratio."""
    from client.table import verdict_lines

    fitted, fit, settle = result.parameters, result.fit, result.settle
    stiffness = fitted.stiffness
    verdict = fit.verdict
    lines = verdict_lines(None if verdict is None else verdict.model_dump())
    lines += [""] if lines else []
    lines.append(f"model  {fitted.stiffness_mode:>12}")
    regions = fitted.regions
    if isinstance(stiffness, dict) and ("axial_scale" in stiffness or regions):
        # material regions, transversely isotropic: the base's families here, the rest below
        lines += [
            f"k {name:<5}{value:12.5g} N/m" for name, value in stiffness.items() if "[" not in name
        ]
        lines = [line.replace(" N/m", "") if "axial_scale" in line else line for line in lines]
        for r in [r for r in regions or [] if r["name"] != "base"]:
            ks = ", ".join(f"{n} {v:.5g}" for n, v in r["stiffness"].items())
            lines.append(
                f"region {r['name']} ({r['cells']} cells, E {r['youngs_modulus']:.4g} Pa): k "
                f"{ks} N/m, kappa {r['volume_stiffness']:.5g} Pa"
            )
    elif isinstance(stiffness, dict) and len(set(stiffness.values())) > 1:
        lines += [f"k {name:<5}{value:12.5g} N/m" for name, value in stiffness.items()]
    else:
        lines += [f"k      {fitted.k:12.5g} N/m"]
    kappa = fitted.volume_stiffness
    if kappa is not None:
        whose = "of the base's cells" if regions else "of every cell"
        lines.append(f"kappa  {kappa:12.5g} Pa (volume stiffness {whose})")
    lines.append(f"d      {fitted.d:12.5g} N s/m")
    dt = settle.dt
    if dt is not None:
        lines.append(f"dt     {dt:12.5g} s (d and the settle steps belong to it)")
    d_min = settle.d_min
    if d_min is not None:
        lines.append(f"d_min  {d_min:12.5g} N s/m (smallest d that settles)")
    lines.append(f"depth  {fitted.depth:12d} layers")
    budget = fitted.step_budget
    if budget is not None:
        met = "meets" if budget.met else "over"
        lines.append(
            f"       a step of its region {max(budget.microseconds):,.0f} us, {met} the "
            f"{budget.budget_us:,.0f} us budget ({budget.backend}, {budget.machine})"
        )
    lines += [f"cost   {fit.cost:12.5g} m (Eq. 2)", ""]
    relative = list(fit.relative_discrepancy)
    h_percent = fit.discrepancy_h
    ratios = list(fit.compliance_ratio or [None] * len(problem.load_cases))
    lines.append(
        f"{'load case':<16}{'relative discrepancy %':>24}{'% of h':>10}{'settle steps':>14}"
        f"{'compliance':>12}"
    )
    for case, rel, disc, steps, ratio in zip(
        problem.load_cases, relative, h_percent, settle.steps, ratios, strict=True
    ):
        lines.append(f"{case.name:<16}{rel:>24.3f}{disc:>10.3f}{steps:>14d}{_ratio(ratio):>12}")
    lines.append(f"{'mean':<16}{_mean(relative):>24.3f}{_mean(h_percent):>10.3f}")
    validation = list(fit.validation_relative_discrepancy)
    if validation:
        lines += [
            "",
            f"{'validation case':<16}{'relative discrepancy %':>24}{'% of h':>10}{'':>14}"
            f"{'compliance':>12}",
        ]
        names = fit.validation_cases or [""] * len(validation)
        unseen = list(fit.validation_compliance_ratio or [None] * len(names))
        for name, rel, disc, ratio in zip(
            names, validation, fit.validation_discrepancy_h, unseen, strict=True
        ):
            lines.append(f"{name:<16}{rel:>24.3f}{disc:>10.3f}{'':>14}{_ratio(ratio):>12}")
        lines.append(
            f"{'mean':<16}{_mean(validation):>24.3f}{_mean(fit.validation_discrepancy_h):>10.3f}"
            "  (never fitted: the honest figure)"
        )
    lines += _field_lines(fitted.field)
    error = result.reference.error
    if error is not None:
        every = list(error) + list(result.reference.validation_error or [])
        refined = result.reference.refinements or 0
        lines += [
            "",
            "reference's estimated error %: "
            + " / ".join(f"{e:.2f}" for e in every)
            + (f" (change from its last refinement, {refined} in all" if refined else " (check")
            + ("; ABOVE 5%: not resolved)" if max(every) > 5 else ")"),
        ]
    total = sum(result.run.seconds.values())
    lines.append("")
    lines.append(
        f"settled: {'yes' if settle.settled else 'NO'}; {result.run.evaluations} cost evaluations "
        f"in {total:.1f} s"
    )
    return "\n".join(lines)


def _field_lines(field: Any) -> list[str]:
    """fpm.stiffness 'field': the four parameters and the field side by side (fitted, never
    fitted, left out) and the smoothness weights tried."""
    if field is None:
        return []

    def figures(values: list[float]) -> str:
        return " / ".join(f"{v:.2f}" for v in values) or "-"

    lines = ["", f"{'model, relative %':<18}{'fit':>24}{'validation':>22}{'left out':>10}"]
    for name, m, returned in (
        ("four parameters", field.four_parameter, not field.returned),
        ("field", field.field, field.returned),
    ):
        lines.append(
            f"{name + (' *' if returned else ''):<18}{figures(m.relative_discrepancy):>24}"
            f"{figures(m.validation_relative_discrepancy):>22}{m.cv_error:>10.2f}"
        )
    tried = ", ".join(
        f"{w:g}: {e:.2f}%" for w, e in zip(field.cv_weights, field.cv_error, strict=True)
    )
    lines.append(f"(* returned) smoothness weight {field.smoothness_weight:g}; left out: {tried}")
    return lines


def _ratio(value: float | None) -> str:
    """A load compliance ratio to 3 decimals, '-' where there is none."""
    return "-" if value is None else f"{value:.3f}"


def _mean(values: Any) -> float:
    values = [float(v) for v in values]
    return sum(values) / len(values) if values else float("nan")
