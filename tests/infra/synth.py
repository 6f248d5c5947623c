"""Synthesis helpers for the infra tests: the stack is built as `cdk synth` builds it (cdk.json context plus
settings given as `-c`, and a settings file when a test names one; never the repository's own)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
# app.py and stacks/ live at the repo root, which is not an installed package.
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))
CLIENT_CIDR = "203.0.113.7/32"
ASSET_HASH_RE = re.compile(r"[0-9a-f]{64}")
# Every optional feature on at once, so one extra synth covers them all.
ALL_OPTIONS = {
    "clientCidr": "198.51.100.0/24",
    "recordSessions": "true",
    "devices": "*",
    "autoStopCron": "0 20 * * ? *",
    "autoStopTimezone": "Europe/Berlin",
    "amiId": "ami-0123456789abcdef0",
    "terminationProtection": "true",
    "availabilityZone": "us-east-1b",
    "instanceType": "g6e.4xlarge",
    "volumeGb": "200",
    "units": "ticks",
    "topicPrefix": "fleet/so101",
    "ros2": "true",
    "dcvIdleTimeoutMinutes": "90",
}


def cdk_json_context() -> dict[str, Any]:
    return json.loads((REPO_ROOT / "cdk.json").read_text())["context"]


class Synth:
    """One synthesized variant: the template dict plus the assertions helper and the stack."""

    def __init__(self, stack: Any, template: Any) -> None:
        self.stack = stack
        self.template = template
        self.json: dict[str, Any] = template.to_json()

    def resources(self, type_: str) -> dict[str, dict[str, Any]]:
        return {k: v for k, v in self.json["Resources"].items() if v["Type"] == type_}

    def one(self, type_: str) -> dict[str, Any]:
        found = self.resources(type_)
        assert len(found) == 1, f"expected one {type_}, found {sorted(found)}"
        return next(iter(found.values()))


def no_lookup(account: str, region: str, instance_type: str) -> list[str]:
    raise AssertionError(f"a test synth must not ask AWS for the offerings of {instance_type} in {region}")


def synthesize(
    outdir: Path,
    region: str | None = None,
    agent_source: Path | None = None,
    *,
    account: str | None = None,
    offerings_lookup: Any = no_lookup,
    context_file: Path | None = None,
    settings_file: Path | None = None,
    **overrides: Any,
) -> Synth:
    """Synthesize the real app (build_app: settings, stack, cdk-nag) with cdk.json context plus overrides.

    Template.from_stack runs the validation plugins, so an unacknowledged cdk-nag finding raises here. With
    an account and a region the AZ is chosen from the instance type's offerings: tests give them as context
    (the cdk.context.json cache) or pass a lookup; AWS is never asked.
    """
    import aws_cdk as cdk
    from aws_cdk.assertions import Template

    from app import build_app

    context = cdk_json_context()
    # A None override leaves the key out (as a deployer who passes no -c for it).
    given = {"clientCidr": CLIENT_CIDR, **overrides}
    context.update({k: v for k, v in given.items() if v is not None})
    with pytest.MonkeyPatch.context() as mp:
        # Environment-agnostic, like a synth without credentials: the template must not depend on who runs it.
        mp.delenv("CDK_DEFAULT_ACCOUNT", raising=False)
        mp.delenv("CDK_DEFAULT_REGION", raising=False)
        if region:
            # As `cdk synth` does when the AWS config names a region.
            mp.setenv("CDK_DEFAULT_REGION", region)
        if account:
            # As the CDK CLI does when it has credentials.
            mp.setenv("CDK_DEFAULT_ACCOUNT", account)
        app = cdk.App(context=context, outdir=str(outdir))
        # agent_source: the agent distribution from another folder (tests that change agent code).
        stack = build_app(
            app,
            agent_source=agent_source,
            # Nothing deployed to compare with (the guard has its own tests, with moto).
            deployed_reader=lambda _stack, _region: None,
            offerings_lookup=offerings_lookup,
            context_file=context_file or outdir / "cdk.context.json",
            settings_file=settings_file,
        )
        template = Template.from_stack(stack)
    return Synth(stack, template)


# The context the CDK CLI adds when it runs the app: validation errors (cdk-nag findings, error annotations)
# are reported to the CLI, which decides per command whether they stop it (deploy and synth do, destroy not).
CLI_CONTEXT = {"@aws-cdk/core:failSynthOnValidationErrors": False}


def app_stack(
    outdir: Path,
    *,
    reader: Any,
    account: str | None = "111111111111",
    region: str = "us-east-1",
    settings_file: Path | None = None,
    **context: Any,
) -> Any:
    """The app as the CDK CLI runs it for `cdk deploy` with credentials: the deployed stack read through
    `reader` (outputs by key), the offerings given, errors left to the caller (`annotations`). Context is
    cdk.json's plus `context` (clientCidr only when given)."""
    import aws_cdk as cdk

    from app import build_app

    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("CDK_DEFAULT_ACCOUNT", raising=False)
        mp.setenv("CDK_DEFAULT_REGION", region)
        if account:
            mp.setenv("CDK_DEFAULT_ACCOUNT", account)
        app = cdk.App(context={**cdk_json_context(), **CLI_CONTEXT, **context}, outdir=str(outdir))
        return build_app(
            app,
            deployed_reader=reader,
            offerings_lookup=lambda _a, _r, _t: [f"{region}b", f"{region}c"],
            context_file=outdir / "cdk.context.json",
            settings_file=settings_file,
        )


def annotations(stack: Any, level: str) -> list[str]:
    """The stack's annotations of `level` ("error" or "warning") as the CDK CLI reads them: from the cloud
    assembly that app.synth() writes (the stack's metadata file)."""
    directory = Path(stack.node.root.synth().directory)
    metadata = json.loads((directory / f"{stack.artifact_id}.metadata.json").read_text())
    return [
        str(e["data"]) for entries in metadata.values() for e in entries if e["type"] == f"aws:cdk:{level}"
    ]


def normalise(template: dict[str, Any]) -> dict[str, Any]:
    """Replace asset hashes and the deployment version (derived from them) so the snapshot changes only when
    the infrastructure does, not with every change of agent code."""
    text = json.dumps(template, sort_keys=True)
    version = template.get("Outputs", {}).get("DeploymentVersion", {}).get("Value")
    if isinstance(version, str):
        text = text.replace(version, "<deployment-version>")
    return json.loads(ASSET_HASH_RE.sub("<asset-hash>", text))
