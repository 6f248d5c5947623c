#!/usr/bin/env python3
"""CDK entry point: read the settings once, validate them, build the one stack, check it with cdk-nag.

The settings come from twin.settings.toml and `-c` (stacks/settings.py). What must stop a deploy but not a
`cdk destroy` (no clientCidr yet, a change that would replace the host or reset a setting nobody asked to
change) becomes an error annotation: the CDK CLI refuses to deploy or synthesize a stack that has one, while
`cdk destroy` needs no settings at all.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import aws_cdk as cdk
from cdk_nag import AwsSolutionsChecks

from stacks.deployed import DeployedReader, DeployedUnknownError, read_deployed_outputs
from stacks.placement import (
    CONTEXT_FILE,
    OfferingsLookup,
    choose_availability_zone,
    read_offerings,
    save_context_value,
)
from stacks.replacement_guard import replacement_refusal
from stacks.settings import (
    ResolvedSettings,
    SettingsError,
    TwinSettings,
    check_context_keys,
    read_settings_file,
    resolve,
    settings_file_path,
)
from stacks.settings_guard import reset_refusal, settings_output
from stacks.twin_stack import TwinStack

PROJECT_ROOT = Path(__file__).resolve().parent
# Where the CDK CLI keeps its lookups, next to cdk.json; the instance type offerings are cached there too.
PROJECT_CONTEXT = PROJECT_ROOT / CONTEXT_FILE
# Marks "use the settings file at the repository root (or -c settingsFile)": tests pass a file or None.
_PROJECT_FILE = Path("<project>")


def build_app(
    app: cdk.App,
    *,
    deployed_reader: DeployedReader | None = None,
    agent_source: Path | None = None,
    offerings_lookup: OfferingsLookup = read_offerings,
    context_file: Path = PROJECT_CONTEXT,
    settings_file: Path | None = _PROJECT_FILE,
) -> TwinStack:
    """Wire the stack into `app`; raises SettingsError for a value that is wrong. Tests pass their own App,
    a reader of the deployed stack's outputs and a lookup of instance type offerings (instead of AWS), a
    cdk.context.json to cache lookups in, the settings file to read (None: none) and the agent
    distribution's folder (default: this repository)."""
    resolved = _resolve_settings(app, settings_file)
    settings = resolved.settings
    region = os.environ.get("CDK_DEFAULT_REGION")
    account = os.environ.get("CDK_DEFAULT_ACCOUNT")
    settings.check_region(region)
    placement = choose_availability_zone(
        instance_type=settings.instance_type,
        pinned=settings.availability_zone,
        account=account,
        region=region,
        context=app.node.try_get_context,
        lookup=offerings_lookup,
        save=lambda key, value: save_context_value(context_file, key, value),
    )
    settings = dataclasses.replace(settings, availability_zone=placement.availability_zone)
    refusals, warning = _compare_with_deployed(
        resolved, settings, region=region, account=account, reader=deployed_reader
    )
    stack = TwinStack(
        app,
        settings.stack_name,
        settings=settings,
        settings_output=settings_output(resolved),
        agent_source=agent_source,
        env=cdk.Environment(account=account, region=region),
        description="so101-twin: SO-101 digital twin host with Amazon DCV and the IoT Core agent",
        termination_protection=False,
    )
    for message in [*settings.deploy_blockers(), *refusals]:
        cdk.Annotations.of(stack).add_error(message)
    if warning:
        cdk.Annotations.of(stack).add_warning_v2("so101-twin:deployed-unchecked", warning)
    if placement.warning:
        cdk.Annotations.of(stack).add_warning_v2("so101-twin:availability-zone-unchecked", placement.warning)
    cdk.Tags.of(stack).add("project", "so101-twin")
    cdk.Validations.of(app).add_plugins(AwsSolutionsChecks(app))
    return stack


def _resolve_settings(app: cdk.App, settings_file: Path | None) -> ResolvedSettings:
    """The settings file (the project's unless a test names one) merged with context, validated."""
    check_context_keys(app.node.get_all_context())
    values = {}
    path = None
    if settings_file == _PROJECT_FILE:
        path, named = settings_file_path(PROJECT_ROOT, app.node.try_get_context)
        values = read_settings_file(path, required=named)
    elif settings_file is not None:
        path = settings_file
        values = read_settings_file(path, required=True)
    return resolve(app.node.try_get_context, values, path)


def _compare_with_deployed(
    resolved: ResolvedSettings,
    settings: TwinSettings,
    *,
    region: str | None,
    account: str | None,
    reader: DeployedReader | None,
) -> tuple[list[str], str | None]:
    """Refusals from comparing with the deployed stack (replacement, silent resets), or a warning that it
    could not be read. Without an account and region from the CDK CLI (no credentials) nothing is compared."""
    if not (region and account):
        return [], None
    reader = reader or read_deployed_outputs
    try:
        outputs = reader(settings.stack_name, region)
        if outputs is None:
            return [], None
        refusals = [
            replacement_refusal(
                stack_name=settings.stack_name,
                deployed_outputs=outputs,
                wanted=settings.instance_fingerprint,
                confirmed=settings.replace_instance,
            ),
            reset_refusal(stack_name=settings.stack_name, deployed_outputs=outputs, resolved=resolved),
        ]
    except DeployedUnknownError as exc:
        return [], (
            f"could not read the deployed {settings.stack_name} in {region} ({exc}); nothing was compared: a "
            "change of availabilityZone, volumeGb, amiId, amiSsmParameter or hostGeneration replaces the "
            "instance and its disk, and a setting left out of twin.settings.toml goes back to its default"
        )
    return [r for r in refusals if r], None


def main() -> int:
    app = cdk.App()
    try:
        build_app(app)
    except SettingsError as exc:
        sys.stderr.write(f"so101-twin: {exc}\n")
        return 2
    app.synth()
    return 0


if __name__ == "__main__":
    sys.exit(main())
