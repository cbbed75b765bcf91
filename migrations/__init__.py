"""Alembic migrations of the narxwatch database (a package, so installed services find them)."""
