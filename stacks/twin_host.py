"""The GPU host: DCV desktop, the agents from S3 assets, an Elastic IP, and its DCV password secret.

How the host is set up and kept current (docs/host.md; docs/deploy.md tells the user's side):
- First boot: the UserData (userdata/user-data.sh) reads the deployment parameter, fetches the assets and
  runs userdata/bootstrap.sh, which ends by signalling the instance's CreationPolicy (and a wait condition
  that carries a failure's reason into the `cdk deploy` output).
- Updates in place: the UserData names only things that never change for the stack, so a deploy that
  changes agent code or settings rewrites the deployment parameter and the State Manager association
  (whose parameters carry the deployment version), and State Manager re-runs the idempotent setup on the
  running host. The instance is neither stopped nor replaced.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path

import jsii
from aws_cdk import (
    Acknowledgment,
    Annotations,
    CfnCreationPolicy,
    CfnResourceSignal,
    CfnTag,
    CfnWaitCondition,
    CfnWaitConditionHandle,
    IgnoreMode,
    RemovalPolicy,
    Stack,
    Validations,
)
from aws_cdk import aws_ec2 as ec2
from aws_cdk import aws_iam as iam
from aws_cdk import aws_s3_assets as s3_assets
from aws_cdk import aws_secretsmanager as secretsmanager
from aws_cdk import aws_ssm as ssm
from constructs import Construct

from stacks.skips import ignore_cfn_lint, skip_checkov

REPO_ROOT = Path(__file__).resolve().parents[1]
USERDATA_DIR = REPO_ROOT / "userdata"
USERDATA_TEMPLATE = USERDATA_DIR / "user-data.sh"
UPDATE_TEMPLATE = USERDATA_DIR / "update.sh"
ROOT_DEVICE = "/dev/sda1"  # the Ubuntu DLAMI's root device
DESKTOP_USER = "ubuntu"
# The first boot's budget: the sum of the step estimates in docs/host.md ("First boot",
# 12-20 min) times about two, for slow mirrors and a busy CDN. Past it the stack rolls back.
BOOT_TIMEOUT_MINUTES = 45
# An update re-runs the same steps on a host that has them all: minutes, but a new agent wheel may be large.
UPDATE_TIMEOUT_SECONDS = 3600
_PLACEHOLDER_RE = re.compile(r"@@([A-Z_]+)@@")
# The instance metadata service answers one network hop: the host's own processes, nothing behind it.
IMDS_HOP_LIMIT = 1
# The hashed dependency lock the host installs from (userdata/install-agent.sh, --require-hashes).
HOST_LOCK = "requirements/host.txt"
# The one Python distribution the instance installs: pyproject.toml builds `twin` (agents/) and
# `twin_robots` (robots/, the model files), with the lock of its dependencies. Docker-style patterns: drop
# everything, re-include those, then drop the development tooling the instance never runs: the layers `rig`
# (local rig, private mosquitto, quota proxy, demo) and `bench` (benchmarks); the `twin demo` and `twin bench`
# commands say so when asked there. pyproject.toml lists neither package, so the package still builds without
# them. Of requirements/, only the host's lock.
AGENT_ASSET_PATTERNS = [
    "*",
    "!pyproject.toml",
    "!README.md",
    "!agents",
    "!robots",
    "!requirements",
    "requirements/*",
    f"!{HOST_LOCK}",
    "agents/twin/rig",
    "agents/twin/bench",
    "robots/tools",
    # The original meshes (16 MB) are only the source the installed visual meshes are made from.
    "robots/so101/meshes/source",
    "**/__pycache__",
    "**/*.pyc",
    "**/*.egg-info",
]
USERDATA_ASSET_PATTERNS = ["user-data.sh", "update.sh", "**/__pycache__"]


@jsii.implements(ec2.IMachineImage)
class _FixedImage:
    """An AMI given by ID (e.g. the Isaac Sim marketplace AMI): region-specific by nature, no lookup."""

    def __init__(self, ami_id: str) -> None:
        self._ami_id = ami_id

    def get_image(self, scope: Construct) -> ec2.MachineImageConfig:
        return ec2.MachineImageConfig(
            image_id=self._ami_id, os_type=ec2.OperatingSystemType.LINUX, user_data=ec2.UserData.for_linux()
        )


def render_template(template: Path, values: Mapping[str, str]) -> str:
    """Fill the @@NAME@@ placeholders of a userdata/ template; every placeholder must be given."""
    text = template.read_text()
    for name, value in values.items():
        placeholder = f"@@{name}@@"
        if placeholder not in text:
            raise KeyError(f"{template.name} has no placeholder {placeholder}")
        text = text.replace(placeholder, value)
    missing = sorted(set(_PLACEHOLDER_RE.findall(text)))
    if missing:
        raise KeyError(f"{template.name}: no value for {missing}")
    return text


def render_user_data(values: Mapping[str, str]) -> str:
    """userdata/user-data.sh with REGION, STACK_NAME, RESOURCE, PARAMETER and HANDLE_URL filled in."""
    return render_template(USERDATA_TEMPLATE, values)


def render_update_commands(version: str) -> list[str]:
    """The association's AWS-RunShellScript lines: userdata/update.sh for this deployment version."""
    return render_template(UPDATE_TEMPLATE, {"VERSION": version}).splitlines()


def deployment_version(*parts: str) -> str:
    """A short, stable id of what the host should run: changes exactly when an asset or a setting does."""
    digest = hashlib.sha256("\n".join(parts).encode()).hexdigest()
    return digest[:12]


class TwinHost(Construct):
    """The instance and what only it uses.

    Attributes: `instance`, `eip`, `password_secret`, `deployment_parameter`, `update_association`,
    `boot_wait`, `deployment_version`.
    """

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
        agent_settings: Mapping[str, str],
        host_generation: int = 1,
        boot_timeout_minutes: int = BOOT_TIMEOUT_MINUTES,
        agent_source: Path = REPO_ROOT,
    ) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)

        self.password_secret = self._password_secret(role)
        agent_asset, scripts_asset = self._assets(stack, role, agent_source)
        self._deployment(stack, role, agent_asset, scripts_asset, agent_settings)
        self._boot_signals(stack, role, boot_timeout_minutes, host_generation)

        # Filled in below, once the instance's logical id (which the UserData signals) exists.
        user_data = ec2.UserData.for_linux(shebang="#!/bin/bash")
        self.instance = self._instance(
            vpc=vpc,
            security_group=security_group,
            role=role,
            instance_type=instance_type,
            volume_gb=volume_gb,
            machine_image=_machine_image(ami_id, ami_ssm_parameter),
            user_data=user_data,
            host_generation=host_generation,
        )
        self._launch_settings(termination_protection, boot_timeout_minutes)
        self._first_boot(stack, role, user_data)
        self.update_association = self._update_association(stack, role)
        self._acknowledge_instance(ami_id, termination_protection)
        self.eip = self._elastic_ip()

    def _password_secret(self, role: iam.IRole) -> secretsmanager.Secret:
        """The DCV user's password, generated by Secrets Manager and readable by the host's role."""
        password_secret = secretsmanager.Secret(
            self,
            "DcvPassword",
            description=f"DCV login password of the desktop user '{DESKTOP_USER}' on the so101-twin host",
            generate_secret_string=secretsmanager.SecretStringGenerator(
                password_length=24, exclude_punctuation=True, include_space=False
            ),
            removal_policy=RemovalPolicy.DESTROY,
        )
        Validations.of(password_secret).acknowledge(
            Acknowledgment(
                id="AwsSolutions-SMG4",
                reason="The secret is the Linux password of the DCV user, set by chpasswd at first boot; "
                "rotating the secret would not change the password on the host and would lock users out.",
            )
        )
        skip_checkov(
            password_secret,
            {
                "CKV_AWS_149": "The AWS managed key for Secrets Manager encrypts it; only this stack's host "
                "role may read it, and a customer key would add cost and a key policy for no gain here."
            },
        )
        password_secret.grant_read(role)
        return password_secret

    def _assets(
        self, stack: Stack, role: iam.IRole, agent_source: Path
    ) -> tuple[s3_assets.Asset, s3_assets.Asset]:
        """The agent distribution and the bootstrap scripts as S3 assets, readable by the host's role."""
        if not (agent_source / HOST_LOCK).is_file():
            Annotations.of(self).add_warning_v2(
                "so101-twin:no-host-lock",
                f"{agent_source / HOST_LOCK} is missing: the host installs the agent only from this hashed "
                "lock (--require-hashes), so its first boot would fail at step agent. Build the lock first.",
            )
        agent_asset = s3_assets.Asset(
            self,
            "AgentPackage",
            path=str(agent_source),
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
        return agent_asset, scripts_asset

    def _deployment(
        self,
        stack: Stack,
        role: iam.IRole,
        agent_asset: s3_assets.Asset,
        scripts_asset: s3_assets.Asset,
        agent_settings: Mapping[str, str],
    ) -> None:
        """The deployment parameter and its version (`deployment_version`, `parameter_name`,
        `deployment_parameter`)."""
        # What the host should run, as KEY=value lines: read by the UserData at first boot and by every
        # in-place update. Its version names the assets' content hashes and the settings, nothing else.
        settings_lines = [f"{key}={value}" for key, value in sorted(agent_settings.items())]
        self.deployment_version = deployment_version(
            agent_asset.asset_hash,
            scripts_asset.asset_hash,
            json.dumps(stack.resolve(settings_lines), sort_keys=True),
        )
        deployment_lines = [
            f"DEPLOYMENT_VERSION={self.deployment_version}",
            f"AGENT_URL={agent_asset.s3_object_url}",
            f"SCRIPTS_URL={scripts_asset.s3_object_url}",
            f"DCV_SECRET_ARN={self.password_secret.secret_arn}",
            f"AWS_REGION={stack.region}",
            f"URL_SUFFIX={stack.url_suffix}",
            *settings_lines,
        ]
        self.parameter_name = f"/so101-twin/{stack.stack_name}/deployment"
        self.deployment_parameter = ssm.StringParameter(
            self,
            "Deployment",
            parameter_name=self.parameter_name,
            description="so101-twin host: asset locations, settings and their version (read by the host)",
            string_value="\n".join(deployment_lines),
        )
        self.deployment_parameter.grant_read(role)

    def _boot_signals(
        self, stack: Stack, role: iam.IRole, boot_timeout_minutes: int, host_generation: int
    ) -> None:
        """What the first boot reports to (`boot_handle`, `boot_wait`), and the role's right to signal."""
        # The first boot's two reports: SignalResource answers the instance's CreationPolicy, on the
        # stack's own ARN only; the wait condition's handle (a pre-signed URL) takes a reason, which
        # `cdk deploy` prints when the boot fails.
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="SignalFirstBoot", actions=["cloudformation:SignalResource"], resources=[stack.stack_id]
            )
        )
        # A new host's boot gets a wait condition of its own: the first host's completed long ago, and a
        # failure posted to it would never reach `cdk deploy`.
        self.boot_handle = CfnWaitConditionHandle(self, _of_generation("BootHandle", host_generation))
        self.boot_wait = CfnWaitCondition(
            self,
            _of_generation("BootWait", host_generation),
            handle=self.boot_handle.ref,
            count=1,
            # Created before the instance launches, so it gets the instance's budget plus launch time.
            timeout=str((boot_timeout_minutes + 10) * 60),
        )

    def _instance(
        self,
        *,
        vpc: ec2.IVpc,
        security_group: ec2.ISecurityGroup,
        role: iam.IRole,
        instance_type: str,
        volume_gb: int,
        machine_image: ec2.IMachineImage,
        user_data: ec2.UserData,
        host_generation: int,
    ) -> ec2.Instance:
        """The GPU instance in the public subnet, with its encrypted gp3 root disk."""
        return ec2.Instance(
            self,
            # A new id is a new logical id, which CloudFormation creates even where the old instance is gone
            # (terminated outside the stack), and a new Name tag; the old resource is deleted after.
            _of_generation("Instance", host_generation),
            vpc=vpc,
            vpc_subnets=ec2.SubnetSelection(subnet_type=ec2.SubnetType.PUBLIC),
            instance_type=ec2.InstanceType(instance_type),
            machine_image=machine_image,
            security_group=security_group,
            role=role,
            user_data=user_data,
            # A public address from the first packet: the Elastic IP is associated only once the
            # instance is complete, i.e. after the boot signalled, and the boot needs the internet.
            associate_public_ip_address=True,
            # IMDSv2 and the hop limit come from the launch template below.
            require_imdsv2=False,
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

    def _launch_settings(self, termination_protection: bool, boot_timeout_minutes: int) -> None:
        """The instance's metadata options (`metadata_options`), termination protection and CreationPolicy."""
        cfn_instance = self.instance.instance
        # IMDSv2 only, answering one hop: set explicitly (EC2's default hop limit depends on the AMI and
        # account settings), so a container or a forwarded packet on the host never gets the role's keys.
        self.metadata_options = ec2.CfnLaunchTemplate(
            self,
            "MetadataOptions",
            launch_template_data=ec2.CfnLaunchTemplate.LaunchTemplateDataProperty(
                metadata_options=ec2.CfnLaunchTemplate.MetadataOptionsProperty(
                    http_endpoint="enabled",
                    http_tokens="required",
                    http_put_response_hop_limit=IMDS_HOP_LIMIT,
                    instance_metadata_tags="disabled",
                )
            ),
        )
        cfn_instance.launch_template = ec2.CfnInstance.LaunchTemplateSpecificationProperty(
            launch_template_id=self.metadata_options.ref,
            version=self.metadata_options.attr_latest_version_number,
        )
        cfn_instance.disable_api_termination = termination_protection
        cfn_instance.cfn_options.creation_policy = CfnCreationPolicy(
            resource_signal=CfnResourceSignal(count=1, timeout=f"PT{boot_timeout_minutes}M")
        )

    def _first_boot(self, stack: Stack, role: iam.IRole, user_data: ec2.UserData) -> None:
        """The UserData of the first boot (userdata/user-data.sh), which signals the instance's logical id."""
        cfn_instance = self.instance.instance
        # Everything the boot reads must exist (and be granted) before the instance starts.
        self.instance.node.add_dependency(self.deployment_parameter, role)
        template = render_user_data(
            {
                "REGION": stack.region,
                "STACK_NAME": stack.stack_name,
                "RESOURCE": cfn_instance.logical_id,
                "PARAMETER": self.parameter_name,
                "HANDLE_URL": self.boot_handle.ref,
            }
        )
        # for_linux adds the shebang line itself.
        user_data.add_commands(template.split("\n", 1)[1])
        skip_checkov(
            self.instance,
            {
                "CKV_AWS_88": "The address is needed for the first boot only (the Elastic IP is associated "
                "after the boot signals); the security group admits DCV from clientCidr and nothing else."
            },
        )

    def _update_association(self, stack: Stack, role: iam.IRole) -> ssm.CfnAssociation:
        """The State Manager association that updates the host in place."""
        # In-place updates: State Manager runs the association again whenever its parameters change, and
        # they change exactly when the deployment version does.
        update_association = ssm.CfnAssociation(
            self,
            "InPlaceUpdate",
            name="AWS-RunShellScript",
            association_name=f"{stack.stack_name}-host-update",
            targets=[
                ssm.CfnAssociation.TargetProperty(key="InstanceIds", values=[self.instance.instance_id])
            ],
            parameters={
                "commands": render_update_commands(self.deployment_version),
                "executionTimeout": [str(UPDATE_TIMEOUT_SECONDS)],
            },
            max_concurrency="1",
            max_errors="0",
        )
        update_association.node.add_dependency(self.deployment_parameter, role)
        return update_association

    def _acknowledge_instance(self, ami_id: str | None, termination_protection: bool) -> None:
        """The instance's acknowledged findings: its AMI reference and, when off, termination protection."""
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

    def _elastic_ip(self) -> ec2.CfnEIP:
        """The host's fixed public address (the DCV URL), associated once the instance is complete."""
        eip = ec2.CfnEIP(self, "Eip", domain="vpc", tags=[CfnTag(key="Name", value="so101-twin-dcv")])
        ec2.CfnEIPAssociation(
            self,
            "EipAssociation",
            allocation_id=eip.attr_allocation_id,
            instance_id=self.instance.instance_id,
        )
        return eip


def _of_generation(construct_id: str, host_generation: int) -> str:
    """The construct id of what belongs to one host: the first host's is the id it always had."""
    return construct_id if host_generation == 1 else f"{construct_id}Gen{host_generation}"


def _machine_image(ami_id: str | None, ami_ssm_parameter: str) -> ec2.IMachineImage:
    """The AMI: the one the deployer pinned, else the public DLAMI parameter, resolved at launch."""
    if ami_id:
        return _FixedImage(ami_id)
    # resolve:ssm:... is resolved by EC2 at launch and the template string never changes, so a new
    # AMI release does not replace the instance (and its disk) on the next deploy.
    return ec2.MachineImage.resolve_ssm_parameter_at_launch(
        ami_ssm_parameter, os=ec2.OperatingSystemType.LINUX
    )
