#!/usr/bin/env python3
"""CDK entry point: read the settings once, validate them, build the one stack, check it with cdk-nag."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import aws_cdk as cdk
from cdk_nag import AwsSolutionsChecks

from stacks.replacement_guard import DeployedReader, check_replacement
from stacks.settings import SettingsError, TwinSettings
from stacks.twin_stack import TwinStack


def build_app(
    app: cdk.App, *, deployed_reader: DeployedReader | None = None, agent_source: Path | None = None
) -> TwinStack:
    """Wire the stack into `app`; raises SettingsError. Tests pass their own App, a reader of the deployed
    stack (instead of AWS) and the agent distribution's folder (default: this repository)."""
    settings = TwinSettings.from_context(app.node.try_get_context)
    region = os.environ.get("CDK_DEFAULT_REGION")
    settings.check_region(region)
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
        env=cdk.Environment(account=os.environ.get("CDK_DEFAULT_ACCOUNT"), region=region),
        description="so101-twin: SO-101 digital twin host with Amazon DCV and the IoT Core agent",
        termination_protection=False,
    )
    if warning:
        cdk.Annotations.of(stack).add_warning_v2("so101-twin:replacement-unchecked", warning)
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
