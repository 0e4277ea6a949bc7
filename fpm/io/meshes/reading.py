"""Mesh files in: meshio's formats and the legacy ones (:mod:`fpm.io.legacy`), and a supplied
reference field read from a file (displacements in m)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MeshError


def mesh_suffix(path: str | Path) -> str | None:
    """The mesh format suffix of ``path`` meshio knows (``.vtu``, ``.vol.gz``, ...), or None."""
    import meshio

    name = Path(path).name.lower()
    known = sorted(meshio.extension_to_filetypes, key=len, reverse=True)
    return next((s for s in known if name.endswith(s)), None)


def legacy_format(path: Path) -> str | None:
    """``"gmsh1"`` for a Gmsh legacy v1 ``.msh`` ($NOD/$ELM), ``"polydata"`` for a legacy VTK
    POLYDATA ``.vtk`` (meshio reads neither), else None; from the file's first lines."""
    suffix = path.suffix.lower()
    if suffix not in (".msh", ".vtk"):
        return None
    try:
        with open(path, "rb") as f:
            head = f.read(4096).decode("latin-1")
    except OSError:
        return None
    if suffix == ".msh" and head.lstrip().startswith("$NOD"):
        return "gmsh1"
    if suffix == ".vtk" and "DATASET POLYDATA" in head.upper():
        return "polydata"
    return None


def read_mesh(path: str | Path) -> Any:
    """The meshio Mesh in ``path``; :class:`MeshError` with the reason when it cannot be read.

    (meshio prints and exits on a file it cannot parse; that is caught here.)
    """
    import meshio

    p = Path(path)
    if not p.is_file():
        raise MeshError(f"{p}: no such mesh file")
    if mesh_suffix(p) is None:
        raise MeshError(
            f"{p}: not a mesh format meshio reads by its suffix (known: .msh, .vtu, .vtk, "
            ".inp, .stl, .obj, .ply, .off, .mesh, .xdmf, ...)"
        )
    legacy = legacy_format(p)
    printed = io.StringIO()
    try:
        if legacy is not None:
            from ..legacy import read_legacy

            return read_legacy(p, legacy)
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            return meshio.read(p)
    except MeshError:
        raise
    except (Exception, SystemExit) as e:
        said = " ".join((printed.getvalue() + " " + str(e)).split()).strip(" 1")
        raise MeshError(f"{p}: cannot read it as a mesh ({said or type(e).__name__})") from None


def read_reference(path: str | Path, load_cases: int) -> list[Any]:
    """A supplied reference field from a file, for ``reference.displacements``: (L, N, 3), m.

    - ``.json``: a list per load case of ``[ux, uy, uz]`` per lattice node, or an object with
      such a ``displacements`` list (what ``fpmcal fem`` writes);
    - ``.vtu`` (or any mesh file meshio reads): one point-data array of shape (N, 3) per load
      case, named ``displacement_J`` or ``fem_displacement_J`` (J = 1..L, as the ``vtu``
      export writes them), or a single ``displacement`` array when there is one load case;
      points in the lattice's node order.

    The shape and finiteness are checked when the spec is loaded (errors at
    ``reference.displacements``); here only what the file holds.

    Raises:
        ValueError: the file holds no such field (the message says what it looked for).
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        data = json.loads(path.read_text())
        if isinstance(data, dict):
            if "displacements" not in data:
                raise ValueError(f"{path}: a JSON reference needs a 'displacements' list")
            data = data["displacements"]
        if not isinstance(data, list):
            raise ValueError(f"{path}: a JSON reference is a list per load case")
        return data
    import meshio

    mesh = meshio.read(path)
    fields = []
    for j in range(1, load_cases + 1):
        names = [f"displacement_{j}", f"fem_displacement_{j}"]
        if load_cases == 1:
            names.append("displacement")
        found = next((n for n in names if n in mesh.point_data), None)
        if found is None:
            have = ", ".join(sorted(mesh.point_data)) or "none"
            raise ValueError(
                f"{path}: no point data {' or '.join(names)} for load case {j} (has: {have})"
            )
        fields.append(np.asarray(mesh.point_data[found], dtype=float).tolist())
    return fields
