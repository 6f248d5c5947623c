"""edge layer (docs/architecture.md): what the SO-101 edge publishes, and the simulator that publishes it."""
