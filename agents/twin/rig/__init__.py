"""rig layer (docs/architecture.md): the whole pipeline on one machine, for `twin demo`, bench and tests."""
