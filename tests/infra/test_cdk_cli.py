"""The pinned CDK CLI (package.json) runs the app exactly as a user would: `cdk synth -c clientCidr=...`."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from .synth import CLIENT_CIDR, REPO_ROOT

CDK = REPO_ROOT / "node_modules" / ".bin" / "cdk"

pytestmark = pytest.mark.slow


def run_cdk(*args: str) -> subprocess.CompletedProcess[str]:
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
    return subprocess.run(
        [str(CDK), *args, "--no-notices", "--no-version-reporting"],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=280,
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
    assert "clientCidr is required" in result.stderr
    assert "-c clientCidr=203.0.113.7/32" in result.stderr
