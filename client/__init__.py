"""Client of the calibration service: the SDK (:class:`Client`) and the ``fpm-client`` script."""

from .sdk import ApiError, Client

__all__ = ["ApiError", "Client"]
