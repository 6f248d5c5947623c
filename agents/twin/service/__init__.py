"""service layer (docs/architecture.md)."""
