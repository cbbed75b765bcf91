"""The REST API: thin routers over :mod:`service.domain`."""
