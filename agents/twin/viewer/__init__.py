"""viewer layer (docs/architecture.md)."""
