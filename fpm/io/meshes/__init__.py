"""Mesh files in, problem specs out: real geometry for the calibration.

A mesh is read with meshio (Gmsh ``.msh``, VTK ``.vtu``/``.vtk``, Abaqus ``.inp``, STL, ...) and
becomes a spec geometry (:mod:`fpm.model.spec`):

- **hexahedra** (8-node; the corners of 20- and 27-node ones) become a ``mesh`` geometry as they
  are: meshio hands them over in VTK node order, which is :mod:`fpm.model.hexahedron`'s; a
  hexahedron numbered inside out (negative volume) is renumbered, and nodes in no hexahedron are
  dropped;
- **tetrahedra** (and wedges and pyramids, split into tetrahedra) and **closed triangle
  surfaces** (quads split in two) are voxelised into a ``voxels`` lattice at a spacing ``h`` the
  user chooses: a cell is solid when its centre lies inside the solid. Both inside tests are
  exact and vectorised over cells (no per-cell Python loop):

  * tetrahedra: barycentric coordinates of the cell centres in each tetrahedron, the candidates
    found by binning every tetrahedron's bounding box onto the lattice;
  * surfaces: parity of the crossings of a vertical ray from each cell centre, the triangles
    binned onto the lattice's columns by their bounding boxes; a ray through an edge or a
    vertex is decided by simulation of simplicity (the ray origin perturbed by (e, e^2)), with
    every edge evaluated once from its lower-numbered vertex, so a crossing on an edge shared
    by two triangles counts exactly once. A surface that does not enclose a volume (an edge
    that belongs to an odd number of triangles) is refused with a clear message.

The lattice is centred on the mesh's bounding box, ``ceil(extent / h)`` cells per axis, and
cropped to the solid cells. :func:`spec_from_mesh` adds the material, fixed nodes and load
cases given as short selector strings (:func:`parse_selector`, :func:`parse_force`) and
``fpmcal spec from-mesh`` is its command line.

The package's modules, one idea each (the names used elsewhere imported from here):
:mod:`.reading`, :mod:`.voxelise`, :mod:`.geometry`, :mod:`.selectors`, :mod:`.conform`,
:mod:`.from_mesh`, :mod:`.sizing` (the spacing for a node count).
"""

from __future__ import annotations

from ..errors import MeshError  # noqa: F401
from .conform import (  # noqa: F401
    KEPT_JACOBIAN,
    conform_lattice,
    conform_spec,
)
from .from_mesh import (  # noqa: F401
    spec_from_mesh,
)
from .geometry import (  # noqa: F401
    geometry_from_mesh,
)
from .reading import (  # noqa: F401
    mesh_suffix,
    read_mesh,
    read_reference,
)
from .selectors import FORCE_HELP, SELECTOR_HELP, parse_force, parse_selector  # noqa: F401
from .sizing import lattice_nodes, spacing_for_nodes  # noqa: F401
from .voxelise import (  # noqa: F401
    lattice,
    voxelise_surface,
    voxelise_tetrahedra,
)
