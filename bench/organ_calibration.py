"""The organ's calibration in a fresh subprocess, for the calibration bench (its part 3,
:mod:`bench.bench_calibration`) and the benches that run the organ the same way: the organ spec
at h with the bench's dt rule (:func:`organ_settings`), the child's calibration
(:func:`organ_child`, run as ``python -m bench.bench_calibration organ H STIFFNESS OUT.json
[PROGRESS.txt]``) and its run with the child's own peak RSS from ``os.wait4``
(:func:`run_organ`)."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DT_RULE_K = 3 * 0.35
"""dt from the stability estimate at k = this * E h (3x the typical fitted k ~ 0.35 E h)."""


def organ_settings(h: float, stiffness: str = "single") -> tuple[dict[str, Any], float]:
    """The organ spec at h with the bench's dt rule; returns (spec, unrounded dt)."""
    import fpm
    from bench.organ import ellipsoid_spec
    from fpm.dynamics.stability import stable_time_step
    from fpm.model.stiffness import spring_stiffness

    if stiffness in ("families+volume", "field"):  # the default model (and the field on it)
        # as a user sends it: no fpm setting but the model (the defaults settle on the
        # distance criterion, max_steps 'auto')
        settings = {} if stiffness == "families+volume" else {"stiffness": stiffness}
        return ellipsoid_spec(h, validation=True, fpm=settings), float("nan")
    problem = fpm.load_problem(ellipsoid_spec(h, fpm={"stiffness": "single"}))
    k = DT_RULE_K * problem.spec.material.youngs_modulus * h
    dt = 0.5 * stable_time_step(problem, spring_stiffness(problem, k))
    settings = {
        "dt": float(f"{dt:.2g}"),
        "max_steps": 5000,
        "settle_tolerance": 1e-6,
        "stiffness": stiffness,
    }
    return ellipsoid_spec(h, fpm=settings), dt


def organ_child(h: float, stiffness: str, out: Path, progress_file: Path | None) -> None:
    """One organ calibration (its timings and figures written to ``out`` as JSON)."""
    import fpm
    from fpm.fitting.calibration import calibrate

    t_start = time.perf_counter()
    spec, dt_raw = organ_settings(h, stiffness)
    log = open(progress_file, "a") if progress_file else None  # noqa: SIM115

    def progress(info: dict[str, Any]) -> None:
        if log is not None and info.get("phase") != "annealing":
            log.write(f"{time.perf_counter() - t0:.1f} {json.dumps(info)}\n")
            log.flush()

    t0 = time.perf_counter()
    problem = fpm.load_problem(spec)
    t_load = time.perf_counter() - t0
    partial = {"nodes": problem.n_nodes, "dt": problem.spec.fpm.dt, "dt_raw": dt_raw}
    out.write_text(json.dumps({**partial, "done": False}))  # what a stopped run still tells
    progress({"phase": "fem"})
    reference = fpm.solve_fem(problem)
    t_fem = time.perf_counter() - t0 - t_load
    result = calibrate(problem, reference=reference, progress=progress)
    wall = time.perf_counter() - t0
    data = {
        "done": True,
        "h": h,
        "stiffness_mode": stiffness,
        "nodes": problem.n_nodes,
        "dt": result.settle.dt,
        "dt_raw": dt_raw,
        "volume_stiffness": result.parameters.volume_stiffness,
        "validation": result.fit.validation_relative_discrepancy,
        "validation_h": result.fit.validation_discrepancy_h,
        "setup": t0 - t_start,
        "load": t_load,
        "fem": t_fem,
        "wall": wall,
        "seconds": result.run.seconds,
        "depth": result.parameters.depth,
        "full_depth": result.parameters.full_depth,
        "k": result.parameters.k,
        "stiffness": result.parameters.stiffness,
        "d": result.parameters.d,
        "d_min": result.settle.d_min,
        "relative": result.fit.relative_discrepancy,
        "steps": result.settle.steps,
        "settled": result.settle.settled,
        "cost": result.fit.cost,
        "static_cost": result.fit.static_cost,
        "warnings": result.warnings,
        "evaluations": result.run.evaluations,
        "damping_runs": result.run.damping_runs,
        "cases": [c.name for c in problem.spec.load_cases],
        "field": None  # fpm.stiffness 'field': the side-by-side figures (not the factors)
        if result.parameters.field is None
        else result.parameters.field.model_dump(exclude={"spring_factor", "kappa_factor"}),
        "self_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    out.write_text(json.dumps(data))


def run_organ(h: float, stiffness: str = "single", timeout: float = 900.0) -> dict[str, Any]:
    """Run :func:`organ_child` in a fresh interpreter; its own peak RSS from ``os.wait4``.

    Returns the child's JSON plus ``peak_mb``, ``process_wall`` (interpreter start included),
    ``cpu`` (user + system s), ``timed_out`` and, on a timeout, the last phase it reported.
    """
    with tempfile.TemporaryDirectory() as tmp:
        out, progress, log = Path(tmp) / "out.json", Path(tmp) / "progress.txt", Path(tmp) / "log"
        env = {
            **os.environ,
            "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        }
        t0 = time.perf_counter()
        with open(log, "w") as sink:
            proc = subprocess.Popen(
                [sys.executable, "-m", "bench.bench_calibration", "organ", str(h), stiffness,
                 str(out), str(progress)],
                cwd=ROOT, env=env, stdout=sink, stderr=subprocess.STDOUT,
            )  # fmt: skip
            timed_out = False
            while True:
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if time.perf_counter() - t0 > timeout:
                    proc.kill()  # this child only (it starts no processes of its own)
                    timed_out = True
                    pid, status, usage = os.wait4(proc.pid, 0)
                    break
                time.sleep(0.2)
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
        elapsed = time.perf_counter() - t0
        info: dict[str, Any] = {}
        if out.exists():
            info = json.loads(out.read_text())
        if not info.get("done") and not timed_out:
            tail = log.read_text()[-2000:]
            raise RuntimeError(f"organ h={h} failed ({proc.returncode}):\n{tail}")
        phases = progress.read_text().splitlines() if progress.exists() else []
    info.update(
        h=h,
        peak_mb=usage.ru_maxrss / 1024,
        process_wall=elapsed,
        cpu=usage.ru_utime + usage.ru_stime,
        timed_out=timed_out,
        last_phase=_where(phases),
    )
    if timed_out:
        info["wall"] = elapsed  # a lower bound: the time reached
    return info


def _where(lines: list[str]) -> str:
    """Where a child got to, from its progress lines ("seconds {json}")."""
    if not lines:
        return "(no progress reported)"
    seconds, info = lines[-1].split(" ", 1)
    last = json.loads(info)
    text = f"phase {last['phase']} at {float(seconds):.0f} s"
    tried = [json.loads(line.split(" ", 1)[1]) for line in lines]
    tried = [t for t in tried if "d" in t]
    if tried:
        settled = sum(t["total_steps"] is not None for t in tried)
        text += (
            f", {len(tried)} d tried in stage 2 ({settled} settled every case; last d "
            f"{tried[-1]['d']:.4g}: {tried[-1]['total_steps'] or 'not settled'})"
        )
    return text
