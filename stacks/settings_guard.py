"""A deploy never silently resets a setting: the stack publishes its settings, and synth compares.

The output `Settings` holds every kept setting's value and, for those that were written down, where: the
settings file or `-c`. A later synth (stacks/deployed.py reads the outputs) refuses a change the deployer
did not ask for this time:

- a value that falls back to its default, while the deployed one was given (a key dropped from the file, or
  a `-c` not repeated);
- a value from the settings file, while the deployed one was given with `-c` only (the file never had it:
  the next deploy without the flag would quietly undo it).

A change written in the file, or passed with `-c`, is a change on purpose. The refusal is an error
annotation, so `cdk deploy` stops on it and `cdk destroy` does not. `twin instance settings` prints the
output as a settings file.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from stacks.deployed import DeployedUnknownError
from stacks.settings import KEPT_KEYS, SETTINGS_FILE, ResolvedSettings, Source, default_values

SETTINGS_OUTPUT = "Settings"
# Bumped when the output's shape changes; a reader refuses a shape it does not know.
OUTPUT_VERSION = 1


def settings_output(resolved: ResolvedSettings) -> str:
    """The `Settings` output's value: {"version", "values": {key: value}, "given": {key: "file" | "-c"}}."""
    values = resolved.settings.file_values()
    return json.dumps(
        {
            "version": OUTPUT_VERSION,
            "values": {k: values[k] for k in KEPT_KEYS},
            "given": resolved.given,
        },
        # In the documented order, which `twin instance settings` keeps.
        separators=(",", ":"),
    )


def parse_settings_output(text: str) -> tuple[dict[str, Any], dict[str, str]]:
    """(values, given) from a `Settings` output; DeployedUnknownError when it cannot be read."""
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise DeployedUnknownError(f"output {SETTINGS_OUTPUT} is not JSON: {text[:80]!r}") from exc
    if not isinstance(doc, dict) or doc.get("version") != OUTPUT_VERSION:
        raise DeployedUnknownError(
            f"output {SETTINGS_OUTPUT} has a shape this version does not read (version "
            f"{doc.get('version') if isinstance(doc, dict) else '?'}, expected {OUTPUT_VERSION})"
        )
    values, given = doc.get("values"), doc.get("given")
    if not isinstance(values, dict) or not isinstance(given, dict):
        raise DeployedUnknownError(f"output {SETTINGS_OUTPUT} lacks its values or given")
    return values, {str(k): str(v) for k, v in given.items()}


def silent_resets(
    deployed_values: Mapping[str, Any], deployed_given: Mapping[str, str], resolved: ResolvedSettings
) -> list[str]:
    """`key: deployed (where) -> new (where)` for every change the deployer did not ask for this time."""
    defaults = default_values()
    wanted = resolved.settings.file_values()
    resets = []
    for key in KEPT_KEYS:
        before = deployed_values.get(key, defaults[key])
        after = wanted[key]
        if _same(before, after):
            continue
        was = deployed_given.get(key, str(Source.DEFAULT))
        now = resolved.sources[key]
        if now is Source.CONTEXT:
            continue
        if (now is Source.DEFAULT and was != str(Source.DEFAULT)) or (
            now is Source.FILE and was == str(Source.CONTEXT)
        ):
            resets.append(f"{key}: {_shown(before)} ({_where(was)}) -> {_shown(after)} ({_where(str(now))})")
    return resets


def reset_refusal(
    *, stack_name: str, deployed_outputs: Mapping[str, str], resolved: ResolvedSettings
) -> str | None:
    """Why this deploy must not go ahead (it would reset settings nobody asked to change), or None."""
    if SETTINGS_OUTPUT not in deployed_outputs:
        return None
    values, given = parse_settings_output(deployed_outputs[SETTINGS_OUTPUT])
    resets = silent_resets(values, given, resolved)
    if not resets:
        return None
    example = resets[0].split(":", 1)[0]
    return (
        f"this deploy would change settings of {stack_name} that it was not given: {'; '.join(resets)}. "
        f"Write the values to keep into {SETTINGS_FILE} (`twin instance settings` prints the deployed "
        f"ones), or pass the new value with -c to change it on purpose (e.g. -c {example}=...)"
    )


def _same(a: Any, b: Any) -> bool:
    # -c gives strings, the file and the output typed values; compare what the file would write.
    return json.dumps(a) == json.dumps(b)


def _shown(value: Any) -> str:
    if value in ("", None):
        return "(not set)"
    if isinstance(value, list):
        return ",".join(str(v) for v in value)
    return json.dumps(value) if isinstance(value, bool) else str(value)


def _where(source: str) -> str:
    return {"default": "default", "file": SETTINGS_FILE, "-c": "-c"}.get(source, source)
