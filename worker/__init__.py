"""worker role (see docs/architecture.md)."""
