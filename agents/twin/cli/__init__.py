"""The `twin` command line (docs/architecture.md: the top layer)."""

from twin.cli.main import main

__all__ = ["main"]
