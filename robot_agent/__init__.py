"""robot_agent role (see docs/architecture.md)."""
