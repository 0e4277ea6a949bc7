"""The problem spec: one pydantic schema for the CLI, the worker and the service.

A spec names a material, a solid (geometry + spring connectivity), the fixed nodes, the load
cases, and the FPM and annealing settings. All quantities are SI (m, N, Pa, kg/m^3, s).
Validation here is what can be checked without building the solid; checks that need the nodes
(a point with no node, a node index out of range, a box with no node) happen in
:func:`fpm.model.problem.load_problem`, which raises the same kind of error with the field's
location.

The schema is split by part of the spec (the names used elsewhere imported from here): :mod:`.base`,
:mod:`.materials`, :mod:`.geometry`, :mod:`.settings`, :mod:`.reference`, :mod:`.problem_spec`.
"""

from __future__ import annotations

from .base import (  # noqa: F401
    EXPORT_VERSION,
    FACES,
    FEM_VERSION,
    MAX_DT,
    MODEL_VERSION,
    UNITS_HINT,
    VOLUME_MODES,
    StiffnessMode,
    lame_constants,
)
from .geometry import (  # noqa: F401
    BoxGeometry,
    MeshGeometry,
    NetworkGeometry,
    Selector,
    VoxelGeometry,
)
from .materials import (  # noqa: F401
    BASE_REGION,
    Material,
    MaterialRegion,
    RegionSelector,
    TransverselyIsotropicMaterial,
    region_names,
)
from .problem_spec import (  # noqa: F401
    ProblemSpec,
)
from .reference import (  # noqa: F401
    ReferenceMesh,
    ReferenceSettings,
)
from .settings import (  # noqa: F401
    MOVES_CAP,
    AnnealingSettings,
    FpmSettings,
    lundy_mees_moves,
)
