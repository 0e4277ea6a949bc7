"""SofaPython3 scene of a fitted FPM lattice, springs and volume term (the ``sofa-python`` export).

This file is the scene's code. :func:`fpm.io.export.sofa_python_scene` writes it out with the
lattice in ``MODEL`` (the JSON export's numbers); run the result with ``runSofa scene.py`` or
``python scene.py`` where SofaPython3 is installed. fpm itself never imports this module (it
needs SOFA); the tests load it with a stand-in ``Sofa.Core.ForceField``.

The scene: positions (``MechanicalObject``), the hexahedra (``MeshTopology``), lumped masses
(``DiagonalMass``), every spring
(``SpringForceField``, kd = 0), the nodal damping d (``UniformVelocityDampingForceField``) at dt
(both the engine's, ``parameters.engine``, where the export has them, else the kernel's), the
fixed nodes (``FixedProjectiveConstraint``), load case 1 (``ConstantForceField``), and the volume
term, which SOFA has no component for, as :class:`VolumeForceField`: per trilinear hexahedron c
the energy 1/2 kappa_c (V_c - V0_c)^2 / V0_c, so

    f_n = -p_c dV_c/dx_n,                         p_c = kappa_c (V_c - V0_c) / V0_c
    df_n = -(kappa_c / V0_c) g_n (g . dx) - p_c (d/dx dV_c/dx_n) dx,   g = dV_c/dx

with V_c in closed form over a_k = sum_n C_kn x_n: V = 8 [a1, a2, a3] + 8/3 ([a1, a4, a5] +
[a4, a2, a6] + [a5, a6, a3]), [a, b, c] = a . (b x c) (docs/physics.md, *The volume term*).
SOFA asks a force field for f (``addForce``), for df = kFactor K dx (``addDForce``) and for
kFactor K as (row, column, value) triplets (``addKToMatrix``), K = df/dx at the positions of the
last ``addForce``.

A fit with ``fpm.loads: "hat"`` judged a force at a surface node as the load it stands for,
shared over the nodes around it; its load cases here are already so shared, and
:func:`applied` shares a force of your own the same way (``MODEL["load_shares"]``), e.g. a
tool's push: ``indices, forces = applied([i], [[0, 0, -0.01]])`` for a ConstantForceField.
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from typing import Any

import numpy as np
import Sofa.Core

MODEL: dict[str, Any] = json.loads("{}")
"""The lattice (the exporter writes it here): nodes, masses, fixed, springs [i, j, L, k],
hexahedra, volume_stiffness, rest_volumes, parameters (d, dt, engine, gravity, loads),
load_cases, and for a hat fit load_shares (each surface node's shares: nodes, indptr, indices,
weights)."""

NATURAL = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
    dtype=float,
)  # fmt: skip
"""(8, 3) natural coordinates of a hexahedron's corners, in the export's corner order."""

COEFFICIENTS = np.stack(
    [NATURAL[:, 0], NATURAL[:, 1], NATURAL[:, 2], NATURAL[:, 0] * NATURAL[:, 1],
     NATURAL[:, 0] * NATURAL[:, 2], NATURAL[:, 1] * NATURAL[:, 2]]
) / 8.0  # fmt: skip
"""(6, 8) C_kn: a_k = sum_n C_kn x_n."""

TRIPLES = ((0, 1, 2, 8.0), (0, 3, 4, 8.0 / 3.0), (3, 1, 5, 8.0 / 3.0), (4, 5, 2, 8.0 / 3.0))
"""V as weighted triple products of a1..a6 (0-based): (p, q, r, weight)."""


def coefficients(x: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(C, 6, 3) a1..a6 of the hexahedra ``corners`` (C, 8) at positions ``x`` (N, 3)."""
    return np.matmul(COEFFICIENTS, x[corners])


def volumes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Volumes (C,) and dV/dx (C, 8, 3) from a1..a6 ``a`` (C, 6, 3)."""
    volume = np.zeros(len(a))
    grad = np.zeros_like(a)
    for p, q, r, w in TRIPLES:
        qr = np.cross(a[:, q], a[:, r])
        volume += w * np.einsum("cd,cd->c", a[:, p], qr)
        grad[:, p] += w * qr
        grad[:, q] += w * np.cross(a[:, r], a[:, p])
        grad[:, r] += w * np.cross(a[:, p], a[:, q])
    return volume, np.einsum("kn,ckd->cnd", COEFFICIENTS, grad)


def gradient_change(a: np.ndarray, da: np.ndarray) -> np.ndarray:
    """(C, 8, 3) the change of dV/dx along ``da`` (C, 6, 3): the Hessian of V times dx (exact:
    dV/da is bilinear in a1..a6)."""
    change = np.zeros_like(a)
    for p, q, r, w in TRIPLES:
        change[:, p] += w * (np.cross(da[:, q], a[:, r]) + np.cross(a[:, q], da[:, r]))
        change[:, q] += w * (np.cross(da[:, r], a[:, p]) + np.cross(a[:, r], da[:, p]))
        change[:, r] += w * (np.cross(da[:, p], a[:, q]) + np.cross(a[:, p], da[:, q]))
    return np.einsum("kn,ckd->cnd", COEFFICIENTS, change)


@contextmanager
def writeable(data: Any) -> Any:
    """The writable array of a SOFA Data (``writeableArray`` in SofaPython3 v22+, else
    ``writeable``)."""
    opener = getattr(data, "writeableArray", None) or data.writeable
    with opener() as array:
        yield array


class VolumeForceField(Sofa.Core.ForceField):
    """The FPM's volume term as a SOFA force field (module docstring)."""

    def __init__(self, hexahedra: Any, kappa: Any, rest_volumes: Any, *args: Any, **kw: Any):
        Sofa.Core.ForceField.__init__(self, *args, **kw)
        self.hexahedra = np.asarray(hexahedra, dtype=np.int64).reshape(-1, 8)
        self.kappa = np.asarray(kappa, dtype=float)
        self.rest_volumes = np.asarray(rest_volumes, dtype=float)
        self.a = np.zeros((len(self.hexahedra), 6, 3))
        self.pressure = np.zeros(len(self.hexahedra))
        self.grad = np.zeros((len(self.hexahedra), 8, 3))

    def forces(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) the volume forces at positions ``x`` (N, 3), N; keeps the state that
        :meth:`dforces` and :meth:`stiffness_triplets` linearise about."""
        self.a = coefficients(x, self.hexahedra)
        volume, self.grad = volumes(self.a)
        self.pressure = self.kappa * (volume - self.rest_volumes) / self.rest_volumes
        out = np.zeros_like(x)
        np.add.at(out, self.hexahedra, -self.pressure[:, None, None] * self.grad)
        return out

    def dforces(self, dx: np.ndarray) -> np.ndarray:
        """(N, 3) K dx, K = df/dx at the last :meth:`forces`."""
        local = dx[self.hexahedra]  # (C, 8, 3)
        dv = np.einsum("cnd,cnd->c", self.grad, local)
        change = gradient_change(self.a, np.matmul(COEFFICIENTS, local))
        df = -(self.kappa / self.rest_volumes * dv)[:, None, None] * self.grad
        df -= self.pressure[:, None, None] * change
        out = np.zeros_like(dx)
        np.add.at(out, self.hexahedra, df)
        return out

    def stiffness_triplets(self, factor: float = 1.0) -> np.ndarray:
        """(T, 3) rows (row, column, factor K[row, column]) over the degrees of freedom 3 n + d;
        K = df/dx at the last :meth:`forces` (entries of a node with itself included)."""
        rows = []
        n_cells = len(self.hexahedra)
        for m in range(8):
            for e in range(3):
                unit = np.zeros((n_cells, 8, 3))
                unit[:, m, e] = 1.0
                dv = self.grad[:, m, e]
                change = gradient_change(self.a, np.matmul(COEFFICIENTS, unit))
                column = -(self.kappa / self.rest_volumes * dv)[:, None, None] * self.grad
                column -= self.pressure[:, None, None] * change  # (C, 8, 3): d f_n / d x_me
                row_index = 3 * self.hexahedra[:, :, None] + np.arange(3)
                col_index = np.broadcast_to(
                    3 * self.hexahedra[:, m, None, None] + e, (n_cells, 8, 3)
                )
                rows.append(
                    np.stack([row_index.ravel(), col_index.ravel(), factor * column.ravel()], 1)
                )
        return np.concatenate(rows) if rows else np.zeros((0, 3))

    def addForce(self, m: Any, forces: Any, pos: Any, vel: Any) -> None:  # noqa: N802 (SOFA's)
        with writeable(forces) as out:
            out[:] += self.forces(np.asarray(pos.value, dtype=float))

    def addDForce(self, m: Any, dforce: Any, dx: Any) -> None:  # noqa: N802
        with writeable(dforce) as out:
            out[:] += m["kFactor"] * self.dforces(np.asarray(dx.value, dtype=float))

    def addKToMatrix(self, mparams: Any, n_nodes: int, n_dofs: int) -> np.ndarray:  # noqa: N802
        return self.stiffness_triplets(mparams["kFactor"])


def applied(indices: Any, forces: Any) -> tuple[list[int], list[list[float]]]:
    """Nodal ``forces`` (K, 3), N, at nodes ``indices`` (K,) as the fit applied them: for a
    hat fit a force on a surface node shared over the nodes around it by its
    ``load_shares`` row (4/9 at the node, 1/9 at each edge neighbour, 1/36 at each diagonal
    one on a flat face), every other force as given. Returns the (indices, forces) of a
    ``ConstantForceField``, nodes ascending."""
    table = MODEL.get("load_shares") or {"nodes": [], "indptr": [0], "indices": [], "weights": []}
    rows = {int(n): r for r, n in enumerate(table["nodes"])}
    total: dict[int, np.ndarray] = {}
    pushes = np.asarray(forces, dtype=float).reshape(-1, 3)
    for i, f in zip(np.ravel(indices), pushes, strict=True):
        r = rows.get(int(i))
        if r is None:
            shares = [(int(i), 1.0)]
        else:
            lo, hi = table["indptr"][r], table["indptr"][r + 1]
            shares = list(zip(table["indices"][lo:hi], table["weights"][lo:hi], strict=True))
        for node, weight in shares:
            total[int(node)] = total.get(int(node), np.zeros(3)) + weight * f
    nodes = sorted(total)
    return nodes, [total[n].tolist() for n in nodes]


def numbers(values: Any) -> list[float]:
    return np.asarray(values, dtype=float).ravel().tolist()


def createScene(root: Any) -> Any:  # noqa: N802 (the name SOFA looks for)
    """The scene: the lattice, its springs, the volume term, d, the fixed nodes, load case 1."""
    p = MODEL["parameters"]
    damping = p.get("engine") or p  # the engine's d and dt where the export has them
    root.dt = damping["dt"]
    root.gravity = list(p["gravity"])
    root.addObject(
        "RequiredPlugin",
        pluginName=[
            "Sofa.Component.StateContainer",
            "Sofa.Component.Topology.Container.Constant",
            "Sofa.Component.Mass",
            "Sofa.Component.SolidMechanics.Spring",
            "Sofa.Component.MechanicalLoad",
            "Sofa.Component.Constraint.Projective",
            "Sofa.Component.ODESolver.Backward",
            "Sofa.Component.LinearSolver.Iterative",
        ],
    )
    root.addObject("DefaultAnimationLoop")
    body = root.addChild("fpm")
    body.addObject("EulerImplicitSolver", rayleighStiffness=0, rayleighMass=0)
    body.addObject("CGLinearSolver", iterations=1000, tolerance=1e-12, threshold=1e-20)
    body.addObject("MechanicalObject", name="dofs", template="Vec3d", position=MODEL["nodes"])
    body.addObject(  # DiagonalMass keeps vertexMass once it has a topology of as many points
        "MeshTopology", name="topology", position="@dofs.position", hexahedra=MODEL["hexahedra"]
    )
    body.addObject("DiagonalMass", name="mass", vertexMass=numbers(MODEL["masses"]))
    springs = [
        [int(i), int(j), float(k), 0.0, float(length)] for i, j, length, k in MODEL["springs"]
    ]
    body.addObject("SpringForceField", name="springs", spring=springs)
    if MODEL.get("volume_stiffness") is not None:
        body.addObject(
            VolumeForceField(
                MODEL["hexahedra"],
                MODEL["volume_stiffness"],
                MODEL["rest_volumes"],
                name="volume",
            )
        )
    body.addObject(
        "UniformVelocityDampingForceField", name="damping", dampingCoefficient=damping["d"],
        implicit=True,
    )  # fmt: skip
    if MODEL["fixed"]:
        body.addObject("FixedProjectiveConstraint", name="fixed", indices=MODEL["fixed"])
    if MODEL["load_cases"]:
        case = MODEL["load_cases"][0]  # the others: MODEL["load_cases"][j]
        body.addObject(
            "ConstantForceField", name="load", indices=case["nodes"], forces=case["forces"]
        )
    return root
