"""transport layer (docs/architecture.md)."""
