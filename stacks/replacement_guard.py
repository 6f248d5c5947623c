"""Refuse a deploy whose settings would replace the twin host, unless the deployer confirms it.

CloudFormation replaces an instance whose availability zone, root volume size or image changes, and the stack
builds a new one when its hostGeneration does: a new root disk, the first boot again (about 15 minutes),
everything kept on the old disk gone. The stack publishes the values it was deployed with as the output
`InstanceFingerprint`, and synth compares them with the new ones (stacks/deployed.py reads the outputs). The
refusal is an error annotation, so `cdk deploy` stops on it while `cdk destroy` (which removes the host
anyway) does not.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

from stacks.deployed import DeployedUnknownError
from stacks.settings import TwinSettings

FINGERPRINT_OUTPUT = "InstanceFingerprint"
CONFIRM_FLAG = "replaceInstance"
_SHOWN = {"availabilityZone": "availabilityZone", "volumeGb": "volumeGb", "image": "amiId/amiSsmParameter"}
# A fingerprint leaves out a key at this value (so stacks deployed before the key existed compare equal): its
# absence on either side means the value, not "not set".
_LEFT_OUT = {"hostGeneration": str(TwinSettings.host_generation)}


def deployed_fingerprint(outputs: Mapping[str, str]) -> dict[str, str] | None:
    """The fingerprint among the deployed stack's outputs; None when it has none (an older stack)."""
    if FINGERPRINT_OUTPUT not in outputs:
        return None
    try:
        value = json.loads(outputs[FINGERPRINT_OUTPUT])
    except ValueError as exc:
        raise DeployedUnknownError(
            f"output {FINGERPRINT_OUTPUT} is not JSON: {outputs[FINGERPRINT_OUTPUT]!r}"
        ) from exc
    return {str(k): str(v) for k, v in value.items()}


def replacing_changes(deployed: Mapping[str, str], wanted: Mapping[str, str]) -> list[str]:
    """Human-readable `key: deployed -> wanted` for every fingerprint entry that differs."""
    changes = []
    for key in sorted(set(deployed) | set(wanted)):
        before, after = (side.get(key, _LEFT_OUT.get(key, "")) for side in (deployed, wanted))
        if before != after:
            changes.append(f"{_SHOWN.get(key, key)}: {before or '(not set)'} -> {after or '(not set)'}")
    return changes


def replacement_refusal(
    *, stack_name: str, deployed_outputs: Mapping[str, str], wanted: Mapping[str, str], confirmed: bool
) -> str | None:
    """Why this deploy must not go ahead (an unconfirmed replacing change), or None."""
    if confirmed:
        return None
    deployed = deployed_fingerprint(deployed_outputs)
    if deployed is None:
        return None
    changes = replacing_changes(deployed, wanted)
    if not changes:
        return None
    return (
        f"this deploy would replace the twin host of {stack_name} ({'; '.join(changes)}): a new root "
        "disk and a new first boot (~15 min), and anything kept on the old disk is lost: the USD "
        "recordings, and servo alarm changes made on the old host while the new one boots (history, "
        "calibrations, your /etc/so101-twin/agent.local.toml and the servo alarms as the new host "
        "boots are in S3 and stay). Keep the "
        f"deployed values (in twin.settings.toml), or confirm with -c {CONFIRM_FLAG}=true"
    )
