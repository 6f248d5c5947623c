"""output layer (docs/architecture.md)."""
