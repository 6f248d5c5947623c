"""tools layer (docs/architecture.md)."""
