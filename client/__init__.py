"""Client of the calibration service: the SDK (:class:`Client`, :func:`spec_from_mesh`) and the
``fpm-client`` script."""

from .sdk import ApiError, Client, spec_from_mesh

__all__ = ["ApiError", "Client", "spec_from_mesh"]
