"""The twin's modes, standard library only.

The agent config, its state document and `twin --help` name them without loading MuJoCo; twin.core.twin
re-exports `TwinMode`, so it has one home.
"""

from __future__ import annotations

from enum import StrEnum


class TwinMode(StrEnum):
    KINEMATIC = "kinematic"
    PHYSICS = "physics"
