"""The GPU host: DCV desktop, the agents from S3 assets, an Elastic IP, and its DCV password secret."""

from __future__ import annotations

import re
from pathlib import Path

import jsii
from aws_cdk import Acknowledgment, CfnTag, IgnoreMode, RemovalPolicy, Stack, Validations
from aws_cdk import aws_ec2 as ec2
from aws_cdk import aws_iam as iam
from aws_cdk import aws_s3_assets as s3_assets
from aws_cdk import aws_secretsmanager as secretsmanager
from constructs import Construct

from stacks.skips import ignore_cfn_lint, skip_checkov

REPO_ROOT = Path(__file__).resolve().parents[1]
USERDATA_DIR = REPO_ROOT / "userdata"
USERDATA_TEMPLATE = USERDATA_DIR / "user-data.sh"
ROOT_DEVICE = "/dev/sda1"  # the Ubuntu DLAMI's root device
DESKTOP_USER = "ubuntu"
_PLACEHOLDER_RE = re.compile(r"@@([A-Z_]+)@@")
# The one Python distribution the instance installs: pyproject.toml builds `twin` (agents/) and
# `twin_robots` (robots/, the model files). Docker-style patterns: drop everything, re-include those, then
# drop the development tooling the instance never runs (benchmark, local rig, demo, private mosquitto; the
# `twin bench` and `twin demo` commands say so when asked there). pyproject.toml does not list
# twin.tools.bench, so the package still builds without it.
AGENT_ASSET_PATTERNS = [
    "*",
    "!pyproject.toml",
    "!README.md",
    "!agents",
    "!robots",
    "agents/twin/tools/bench",
    "agents/twin/tools/rig.py",
    "agents/twin/tools/demo.py",
    "agents/twin/tools/mosquitto.py",
    "robots/tools",
    # The original meshes (16 MB) are only the source the installed visual meshes are made from.
    "robots/so101/meshes/source",
    "**/__pycache__",
    "**/*.pyc",
    "**/*.egg-info",
]
USERDATA_ASSET_PATTERNS = ["user-data.sh", "**/__pycache__"]


@jsii.implements(ec2.IMachineImage)
class _FixedImage:
    """An AMI given by ID (e.g. the Isaac Sim marketplace AMI): region-specific by nature, no lookup."""

    def __init__(self, ami_id: str) -> None:
        self._ami_id = ami_id

    def get_image(self, scope: Construct) -> ec2.MachineImageConfig:
        return ec2.MachineImageConfig(
            image_id=self._ami_id, os_type=ec2.OperatingSystemType.LINUX, user_data=ec2.UserData.for_linux()
        )


def render_user_data(values: dict[str, str]) -> str:
    """Fill the @@NAME@@ placeholders of userdata/user-data.sh; every placeholder must be given."""
    text = USERDATA_TEMPLATE.read_text()
    for name, value in values.items():
        placeholder = f"@@{name}@@"
        if placeholder not in text:
            raise KeyError(f"{USERDATA_TEMPLATE.name} has no placeholder {placeholder}")
        text = text.replace(placeholder, value)
    missing = sorted(set(_PLACEHOLDER_RE.findall(text)))
    if missing:
        raise KeyError(f"{USERDATA_TEMPLATE.name}: no value for {missing}")
    return text


class TwinHost(Construct):
    """The instance and what only it uses. Attributes: `instance`, `eip`, `password_secret`."""

    def __init__(
        self,
        scope: Construct,
        id_: str,
        *,
        vpc: ec2.IVpc,
        security_group: ec2.ISecurityGroup,
        role: iam.IRole,
        instance_type: str,
        volume_gb: int,
        ami_ssm_parameter: str,
        ami_id: str | None,
        termination_protection: bool,
        agent_settings: dict[str, str],
    ) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)

        self.password_secret = secretsmanager.Secret(
            self,
            "DcvPassword",
            description=f"DCV login password of the desktop user '{DESKTOP_USER}' on the so101-twin host",
            generate_secret_string=secretsmanager.SecretStringGenerator(
                password_length=24, exclude_punctuation=True, include_space=False
            ),
            removal_policy=RemovalPolicy.DESTROY,
        )
        Validations.of(self.password_secret).acknowledge(
            Acknowledgment(
                id="AwsSolutions-SMG4",
                reason="The secret is the Linux password of the DCV user, set by chpasswd at first boot; "
                "rotating the secret would not change the password on the host and would lock users out.",
            )
        )
        skip_checkov(
            self.password_secret,
            {
                "CKV_AWS_149": "The AWS managed key for Secrets Manager encrypts it; only this stack's host "
                "role may read it, and a customer key would add cost and a key policy for no gain here."
            },
        )
        self.password_secret.grant_read(role)

        agent_asset = s3_assets.Asset(
            self,
            "AgentPackage",
            path=str(REPO_ROOT),
            exclude=AGENT_ASSET_PATTERNS,
            ignore_mode=IgnoreMode.DOCKER,
        )
        scripts_asset = s3_assets.Asset(
            self, "BootstrapScripts", path=str(USERDATA_DIR), exclude=USERDATA_ASSET_PATTERNS
        )
        # Exactly the two objects, rather than asset.grant_read's bucket-wide GetObject*/List*.
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="ReadBootstrapAssets",
                actions=["s3:GetObject"],
                resources=[
                    f"arn:{stack.partition}:s3:::{asset.s3_bucket_name}/{asset.s3_object_key}"
                    for asset in (agent_asset, scripts_asset)
                ],
            )
        )

        settings_env = "\n".join(f"{key}={value}" for key, value in sorted(agent_settings.items()))
        user_data = ec2.UserData.custom(
            render_user_data(
                {
                    "REGION": stack.region,
                    "AGENT_URL": agent_asset.s3_object_url,
                    "SCRIPTS_URL": scripts_asset.s3_object_url,
                    "SECRET_ARN": self.password_secret.secret_arn,
                    "SETTINGS_ENV": settings_env,
                }
            )
        )

        if ami_id:
            machine_image: ec2.IMachineImage = _FixedImage(ami_id)
        else:
            # resolve:ssm:... is resolved by EC2 at launch and the template string never changes, so a new
            # AMI release does not replace the instance (and its disk) on the next deploy.
            machine_image = ec2.MachineImage.resolve_ssm_parameter_at_launch(
                ami_ssm_parameter, os=ec2.OperatingSystemType.LINUX
            )

        self.instance = ec2.Instance(
            self,
            "Instance",
            vpc=vpc,
            vpc_subnets=ec2.SubnetSelection(subnet_type=ec2.SubnetType.PUBLIC),
            instance_type=ec2.InstanceType(instance_type),
            machine_image=machine_image,
            security_group=security_group,
            role=role,
            user_data=user_data,
            require_imdsv2=True,
            detailed_monitoring=True,
            ebs_optimized=True,
            block_devices=[
                ec2.BlockDevice(
                    device_name=ROOT_DEVICE,
                    volume=ec2.BlockDeviceVolume.ebs(
                        volume_gb,
                        encrypted=True,
                        volume_type=ec2.EbsDeviceVolumeType.GP3,
                        delete_on_termination=True,
                    ),
                )
            ],
        )
        self.instance.instance.disable_api_termination = termination_protection
        if not ami_id:
            ignore_cfn_lint(self.instance, ["E1152"])
            Validations.of(self.instance).acknowledge(
                Acknowledgment(
                    id="CloudFormation-Validate::E1152",
                    reason="ImageId is deliberately 'resolve:ssm:<public DLAMI parameter>': EC2 resolves "
                    "it at launch, so the template stays stable and a new AMI release never replaces the "
                    "instance.",
                )
            )
        else:
            Validations.of(self.instance).acknowledge(
                Acknowledgment(
                    id="CloudFormation-Validate::W9010",
                    reason="The deployer pinned this AMI with -c amiId (e.g. the Isaac Sim marketplace AMI, "
                    "which has no public SSM parameter); AMI IDs are per region by nature.",
                )
            )
        if not termination_protection:
            Validations.of(self.instance).acknowledge(
                Acknowledgment(
                    id="AwsSolutions-EC29",
                    reason="Off by default so `cdk destroy` removes everything; the root disk holds no data "
                    "that is not rebuilt from the stack. Turn on with -c terminationProtection=true.",
                )
            )

        self.eip = ec2.CfnEIP(self, "Eip", domain="vpc", tags=[CfnTag(key="Name", value="so101-twin-dcv")])
        ec2.CfnEIPAssociation(
            self,
            "EipAssociation",
            allocation_id=self.eip.attr_allocation_id,
            instance_id=self.instance.instance_id,
        )
