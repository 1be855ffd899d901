"""server role (see docs/architecture.md)."""
