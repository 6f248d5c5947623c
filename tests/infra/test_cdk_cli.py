"""The pinned CDK CLI (package.json) runs the app exactly as a user would: `cdk synth -c clientCidr=...`,
and `cdk destroy` with no flags at all."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from .synth import CLIENT_CIDR, REPO_ROOT

CDK = REPO_ROOT / "node_modules" / ".bin" / "cdk"

pytestmark = pytest.mark.slow


def run_cdk(
    *args: str, cwd: Path = REPO_ROOT, extra_env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    if not CDK.exists():
        pytest.fail(f"{CDK} is missing: `make setup` installs the CDK CLI pinned in package.json (npm ci)")
    env = {
        **os.environ,
        "JSII_SILENCE_WARNING_END_OF_LIFE_NODE_VERSION": "20",
        "CDK_DISABLE_VERSION_CHECK": "1",
        # No credentials, as in CI: the synth must not need an AWS account.
        "AWS_EC2_METADATA_DISABLED": "true",
    }
    for key in ("CDK_DEFAULT_ACCOUNT", "CDK_DEFAULT_REGION", "AWS_PROFILE"):
        env.pop(key, None)
    env.update(extra_env or {})
    return subprocess.run(
        [str(CDK), *args, "--no-notices", "--no-version-reporting"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def test_cdk_synth_outputs_the_dcv_url_from_the_elastic_ip(tmp_path: Path) -> None:
    result = run_cdk("synth", "-c", f"clientCidr={CLIENT_CIDR}", "--quiet", "-o", str(tmp_path))
    assert result.returncode == 0, result.stderr[-3000:]
    template = json.loads((tmp_path / "So101TwinStack.template.json").read_text())
    url = template["Outputs"]["DcvUrl"]["Value"]["Fn::Join"][1]
    eip = url[1]["Fn::GetAtt"]
    assert url[0] == "https://" and url[2] == ":8443/#console"
    assert template["Resources"][eip[0]]["Type"] == "AWS::EC2::EIP" and eip[1] == "PublicIp"
    assert {"DcvUrl", "InstanceId", "IotEndpoint", "DcvPasswordSecret", "SsmSessionCommand"} <= set(
        template["Outputs"]
    )


def test_cdk_synth_without_client_cidr_says_what_to_pass(tmp_path: Path) -> None:
    result = run_cdk("synth", "--quiet", "-o", str(tmp_path))
    assert result.returncode != 0
    said = result.stdout + result.stderr
    assert "clientCidr is required" in said
    assert "-c clientCidr=203.0.113.7/32" in said


def _checkout(root: Path) -> Path:
    """A checkout of the app in `root`: app.py and stacks/ copied (they locate the project from their own
    path, so cdk.context.json and the assets are the copy's), the rest linked. No twin.settings.toml."""
    root.mkdir()
    for name in ("app.py", "cdk.json"):
        shutil.copy2(REPO_ROOT / name, root / name)
    shutil.copytree(REPO_ROOT / "stacks", root / "stacks", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("agents", "robots", "requirements", "userdata", "pyproject.toml", "README.md", ".venv"):
        (root / name).symlink_to(REPO_ROOT / name)
    return root


def test_cdk_destroy_needs_no_flags(tmp_path: Path) -> None:
    """`cdk destroy` with no -c and no settings file deletes the deployed stack. The CDK CLI talks to AWS
    through its SDK, which honours AWS_ENDPOINT_URL: moto's server stands in for CloudFormation and STS."""
    import boto3
    from moto_s3 import REGION, MotoS3

    checkout = _checkout(tmp_path / "checkout")
    aws = MotoS3()
    try:
        cloudformation = boto3.client(
            "cloudformation",
            endpoint_url=aws.endpoint,
            region_name=REGION,
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
        )
        template = {"Resources": {"Topic": {"Type": "AWS::SNS::Topic"}}}
        cloudformation.create_stack(StackName="So101TwinStack", TemplateBody=json.dumps(template))
        result = run_cdk(
            "destroy",
            "--force",
            cwd=checkout,
            extra_env={
                "AWS_ENDPOINT_URL": aws.endpoint,
                "AWS_ACCESS_KEY_ID": "testing",
                "AWS_SECRET_ACCESS_KEY": "testing",
                "AWS_REGION": REGION,
                "AWS_DEFAULT_REGION": REGION,
            },
        )
        assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
        summaries = cloudformation.list_stacks()["StackSummaries"]
        assert [(s["StackName"], s["StackStatus"]) for s in summaries] == [
            ("So101TwinStack", "DELETE_COMPLETE")
        ]
    finally:
        aws.close()
