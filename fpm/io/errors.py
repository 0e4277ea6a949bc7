"""The errors of the file formats in and out, in a module of their own so that every reader and
writer of :mod:`fpm.io` raises the same class without importing another reader for it."""


class MeshError(ValueError):
    """A mesh file that cannot become a solid (unreadable, open surface, no cells, ...)."""


class ExportError(ValueError):
    """Parameters that do not fit the spec's lattice, or an unknown format."""
