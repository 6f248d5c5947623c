#!/usr/bin/env python3
"""CDK entry point: read the settings once, validate them, build the one stack, check it with cdk-nag."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import aws_cdk as cdk
from cdk_nag import AwsSolutionsChecks

from stacks.placement import (
    CONTEXT_FILE,
    OfferingsLookup,
    choose_availability_zone,
    read_offerings,
    save_context_value,
)
from stacks.replacement_guard import DeployedReader, check_replacement
from stacks.settings import SettingsError, TwinSettings
from stacks.twin_stack import TwinStack

# Where the CDK CLI keeps its lookups, next to cdk.json; the instance type offerings are cached there too.
PROJECT_CONTEXT = Path(__file__).resolve().parent / CONTEXT_FILE


def build_app(
    app: cdk.App,
    *,
    deployed_reader: DeployedReader | None = None,
    agent_source: Path | None = None,
    offerings_lookup: OfferingsLookup = read_offerings,
    context_file: Path = PROJECT_CONTEXT,
) -> TwinStack:
    """Wire the stack into `app`; raises SettingsError. Tests pass their own App, a reader of the deployed
    stack and a lookup of instance type offerings (instead of AWS), a cdk.context.json to cache lookups in,
    and the agent distribution's folder (default: this repository)."""
    settings = TwinSettings.from_context(app.node.try_get_context)
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
    warning = check_replacement(
        stack_name=settings.stack_name,
        wanted=settings.instance_fingerprint,
        confirmed=settings.replace_instance,
        reader=deployed_reader,
    )
    stack = TwinStack(
        app,
        settings.stack_name,
        settings=settings,
        agent_source=agent_source,
        env=cdk.Environment(account=account, region=region),
        description="so101-twin: SO-101 digital twin host with Amazon DCV and the IoT Core agent",
        termination_protection=False,
    )
    if warning:
        cdk.Annotations.of(stack).add_warning_v2("so101-twin:replacement-unchecked", warning)
    if placement.warning:
        cdk.Annotations.of(stack).add_warning_v2("so101-twin:availability-zone-unchecked", placement.warning)
    cdk.Tags.of(stack).add("project", "so101-twin")
    cdk.Validations.of(app).add_plugins(AwsSolutionsChecks(app))
    return stack


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
