"""Worked examples of systems defined outside daof, as a user writes them (docs/custom_system.md)."""
