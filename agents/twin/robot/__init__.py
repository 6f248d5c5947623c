"""robot layer (docs/architecture.md)."""
