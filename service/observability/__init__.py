"""Prometheus metrics, structured logs and request ids for the service."""
