"""What a deployed twin stack runs with: its `Settings` output, read back as a settings file.

The stack (stacks/settings_guard.py) publishes every kept setting's value and, for those the deployer wrote
down, where (`file`: twin.settings.toml, `-c`: the command line) as one JSON output. `twin instance settings`
prints it as a twin.settings.toml: the given settings as live lines, the defaults commented out, so saving it
keeps the deployment as it is (tests/test_instance.py reads the printed file back through the stack's own
settings loader).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

OUTPUT_SETTINGS = "Settings"
# The output's shape (stacks/settings_guard.py, OUTPUT_VERSION).
SETTINGS_VERSION = 1


class DeployedSettingsError(ValueError):
    """The output is missing or has a shape this version cannot read; the message says what to do."""


@dataclass(frozen=True)
class DeployedSettings:
    """Each kept setting's value in the documented order, and where the given ones came from."""

    values: Mapping[str, Any]
    given: Mapping[str, str]

    def to_toml(self, header: str = "") -> str:
        lines = [f"# {line}" if line else "#" for line in header.splitlines()]
        for key, value in self.values.items():
            source = self.given.get(key)
            if source is None:
                lines.append(f"# {key} = {toml_value(value)}  # default")
            else:
                note = (
                    "  # given with -c: keep it here, or the next deploy resets it" if source == "-c" else ""
                )
                lines.append(f"{key} = {toml_value(value)}{note}")
        return "\n".join(lines) + "\n"


def parse_deployed_settings(text: str | None, stack_name: str) -> DeployedSettings:
    """The stack's Settings output; DeployedSettingsError when it lacks one or cannot be read."""
    if not text:
        raise DeployedSettingsError(
            f"stack {stack_name} has no {OUTPUT_SETTINGS} output: it was deployed by an older version; "
            "deploy it once with this version (`cdk deploy`), then ask again"
        )
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise DeployedSettingsError(
            f"the {OUTPUT_SETTINGS} output of {stack_name} is not JSON ({exc})"
        ) from exc
    if not isinstance(doc, dict) or doc.get("version") != SETTINGS_VERSION:
        raise DeployedSettingsError(
            f"the {OUTPUT_SETTINGS} output of {stack_name} has a shape this version does not read; update "
            "so101-twin to the version that deployed it"
        )
    values, given = doc.get("values"), doc.get("given")
    if not isinstance(values, dict) or not isinstance(given, dict):
        raise DeployedSettingsError(f"the {OUTPUT_SETTINGS} output of {stack_name} lacks its values")
    return DeployedSettings(values=values, given={str(k): str(v) for k, v in given.items()})


def toml_value(value: Any) -> str:
    """A setting's value in TOML: strings, booleans, whole numbers and lists of strings are all it holds."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return str(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return json.dumps(str(value))
