"""The service's logic, independent of HTTP: routers call these functions with a session."""
