"""The SOFA exports: an XML scene (``sofa``) and a SofaPython3 scene (``sofa-python``).

- ``sofa``: a SOFA scene (``.scn``) with the positions (``MechanicalObject``), the lumped masses
  (``DiagonalMass vertexMass``), every spring with its stiffness (``SpringForceField spring="i j
  ks kd L"``, kd = 0), the nodal damping d (``UniformVelocityDampingForceField``; the engine's d
  and dt, ``parameters.engine``, where they could be computed, else the kernel's), the fixed
  nodes (``FixedProjectiveConstraint``) and the load cases (``ConstantForceField``; the first
  one active). docs/physics.md, *Engines*, says why each component and where SOFA defines it.
  SOFA has no component for the volume term (a penalty on each trilinear hexahedron's volume):
  a scene of a families+volume fit says so in a comment (:data:`SOFA_NO_VOLUME`), and
  :func:`fpm.io.export.export_warnings` warns;
- ``sofa-python``: a SofaPython3 scene (``.py``) with the same components plus the volume term
  as a ``Sofa.Core.ForceField`` subclass in NumPy (:mod:`fpm.io.sofa_scene`: addForce,
  addDForce, addKToMatrix), the lattice's numbers in the file: the whole default model in SOFA.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from .json_format import engine_parameters, to_json
from .lattice import Lattice, Parameters

SOFA_NO_VOLUME = (
    "SOFA has no XML component for this model's volume term (1/2 kappa (V - V0)^2 / V0 per "
    "trilinear hexahedron): this scene has the springs only and is softer in compression than "
    "the fitted model; export format sofa-python for a SofaPython3 scene that carries the "
    "volume term as a Python ForceField"
)


SOFA_PLUGINS = {
    "Sofa.Component.StateContainer": "MechanicalObject",
    "Sofa.Component.Topology.Container.Constant": "MeshTopology",
    "Sofa.Component.Mass": "DiagonalMass",
    "Sofa.Component.SolidMechanics.Spring": "SpringForceField",
    "Sofa.Component.MechanicalLoad": "UniformVelocityDampingForceField ConstantForceField",
    "Sofa.Component.Constraint.Projective": "FixedProjectiveConstraint",
    "Sofa.Component.ODESolver.Backward": "EulerImplicitSolver",
    "Sofa.Component.LinearSolver.Iterative": "CGLinearSolver",
}
"""The SOFA modules the scene loads, with the components it takes from each."""


def _numbers(values: Any) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=float).ravel())


def _indices(values: Any) -> str:
    return " ".join(str(int(v)) for v in np.asarray(values).ravel())


def sofa_scene(lattice: Lattice) -> str:
    """The ``sofa`` export: a scene SOFA (v24.06 or later) loads (module docstring)."""
    problem, p = lattice.problem, lattice.params
    springs = np.column_stack(
        [
            problem.solid.springs.astype(float),
            lattice.stiffness,
            np.zeros(len(lattice.stiffness)),
            problem.rest_lengths,
        ]
    )
    spring_text = " ".join(
        f"{int(i)} {int(j)} {ks!r} 0 {length!r}" for i, j, ks, _, length in springs.tolist()
    )
    g = " ".join(repr(float(v)) for v in problem.spec.fpm.gravity)
    engine = engine_parameters(lattice)
    d, dt = (engine["d"], engine["dt"]) if engine else (p.d, p.dt)
    lines = [
        '<?xml version="1.0"?>',
        _comment(
            f"FPM lattice {problem.spec.name}: SI units (m, kg, s, N). {problem.n_nodes} nodes, "
            f"{len(springs)} springs (spring = i j ks kd L: ks in N/m, kd = 0, L the rest "
            f"length in m); stiffness {_fmt_stiffness(p.stiffness)} N/m; "
            + _sofa_damping_words(p, engine)
            + "; the FPM's perturbed list has no SOFA counterpart: SOFA moves every node (full "
            "depth)." + ("" if lattice.volume is None else " " + SOFA_NO_VOLUME + ".")
        ),
        f'<Node name="root" dt={quoteattr(repr(dt))} gravity="{g}">',
    ]
    lines += [
        f'    <RequiredPlugin name="{plugin}"/> <!-- {what} -->'
        for plugin, what in SOFA_PLUGINS.items()
    ]
    lines += [
        "    <DefaultAnimationLoop/>",
        f'    <Node name="{_identifier(problem.spec.name)}">',
        '        <EulerImplicitSolver name="odesolver" rayleighStiffness="0" rayleighMass="0"/>',
        '        <CGLinearSolver name="linearsolver" iterations="1000" tolerance="1e-12" '
        'threshold="1e-20"/>',
        '        <MechanicalObject name="dofs" template="Vec3d" '
        f'position="{_numbers(problem.nodes)}"/>',
        '        <MeshTopology name="topology" position="@dofs.position" '
        f'hexahedra="{_indices(lattice.hexahedra)}"/>',
        f'        <DiagonalMass name="mass" vertexMass="{_numbers(problem.solid.masses)}"/>',
        f'        <SpringForceField name="springs" spring="{spring_text}"/>',
        '        <UniformVelocityDampingForceField name="damping" '
        f'dampingCoefficient="{d!r}" implicit="true"/>',
    ]
    fixed = np.flatnonzero(problem.fixed)
    if len(fixed):
        lines.append(
            f'        <FixedProjectiveConstraint name="fixed" indices="{_indices(fixed)}"/>'
        )
    for j, case in enumerate(problem.load_cases):
        element = (
            f"<ConstantForceField name={quoteattr(f'load case {j + 1}')} "
            f'indices="{_indices(case.nodes)}" forces="{_numbers(case.forces)}"/>'
        )
        if j == 0:
            lines.append("        " + _comment(f"load case 1: {case.name}"))
            lines.append(f"        {element}")
        else:
            lines.append(
                "        "
                + _comment(f"load case {j + 1}: {case.name} (uncomment to apply) {element}")
            )
    lines += ["    </Node>", "</Node>", ""]
    return "\n".join(lines)


def _sofa_damping_words(p: Parameters, engine: dict[str, float] | None) -> str:
    """What a SOFA scene says of its d and dt (the engine's, where the export has them)."""
    kernel = (
        f"the calibration's d = {p.d!r} N s/m was fitted at dt = {p.dt!r} s for the FPM's "
        "node-by-node step"
    )
    if engine is None:
        return f"nodal damping: {kernel} (choose d again for this integrator and time step)"
    return (
        f"nodal damping d = {engine['d']!r} N s/m and dt = {engine['dt']!r} s: the engine's "
        "(the export's parameters.engine), the fastest-settling pair of the explicit all-at-once "
        "step at rest, each mode's error shrinking by "
        f"{engine['decay_per_step']!r} a step; under SOFA's implicit Euler every dt is stable "
        "and this d is close to the slowest mode's critical damping (2 m w_min), so it settles "
        f"near fastest at this dt as well ({kernel})"
    )


def _identifier(text: str) -> str:
    """``text`` as a SOFA node name (letters, digits, underscores), "fpm" if nothing is left."""
    return re.sub(r"[^0-9A-Za-z_]+", "_", text).strip("_") or "fpm"


def _comment(text: str) -> str:
    """An XML comment of ``text`` (which may not hold "--")."""
    while "--" in text:
        text = text.replace("--", "- -")
    return f"<!-- {text.rstrip('-')} -->"


def _fmt_stiffness(stiffness: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:.6g}" for name, value in stiffness.items())


def sofa_python_scene(lattice: Lattice) -> str:
    """The ``sofa-python`` export: :mod:`fpm.io.sofa_scene`'s code with the lattice in MODEL."""
    import json

    template = (Path(__file__).parents[1] / "sofa_scene.py").read_text()
    doc = to_json(lattice)
    model = {
        key: doc[key]
        for key in (
            "name", "units", "parameters", "nodes", "masses", "fixed", "springs", "hexahedra",
            "volume_stiffness", "rest_volumes",
        )
    }  # fmt: skip
    model["load_cases"] = [
        {k: case[k] for k in ("name", "nodes", "forces")} for case in doc["load_cases"]
    ]
    if "load_shares" in doc:  # a hat fit: applied() spreads a force as the fit did
        model["load_shares"] = doc["load_shares"]
    placeholder = 'MODEL: dict[str, Any] = json.loads("{}")'
    if placeholder not in template:
        raise RuntimeError("fpm/io/sofa_scene.py lost its MODEL line")
    p = lattice.params
    words = textwrap.wrap(
        _sofa_damping_words(p, doc["parameters"]["engine"]) + ".",
        width=97,
        break_long_words=False,
        break_on_hyphens=False,
    )
    header = (
        f"# FPM lattice {lattice.problem.spec.name!r} for SofaPython3: SI units (m, kg, s, N).\n"
        f"# {lattice.problem.n_nodes} nodes, {len(lattice.stiffness)} springs.\n"
        + "".join(f"# {line}\n" for line in words)
        + "# Run: runSofa this_file.py (or python with SofaPython3). Generated by fpm.\n"
    )
    return header + template.replace(
        placeholder, f"MODEL: dict[str, Any] = json.loads({json.dumps(model)!r})"
    )
