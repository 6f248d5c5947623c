"""The stack's bucket: Delta tables the host's agent writes under `history/` (docs/history.md), each arm's
LeRobot calibration under `calibration/<device>.json`, which `twin calibration push` writes and the agent
reads (docs/agent.md, "Calibration"), and under `host/` the copy of the operator's own agent settings the host
keeps, so that a host replacing it starts with them (docs/deploy.md, "Changes that replace the instance")."""

from __future__ import annotations

from typing import cast

from aws_cdk import Acknowledgment, Duration, RemovalPolicy, Stack, Validations
from aws_cdk import aws_iam as iam
from aws_cdk import aws_s3 as s3
from constructs import Construct

from stacks.skips import skip_checkov

HISTORY_PREFIX = "history"
CALIBRATION_PREFIX = "calibration"
HOST_STATE_PREFIX = "host"
# Under it: /etc/so101-twin/agent.local.toml (userdata/save-local-config.sh), and each host's copy of the
# agent's servo alarm state, <host id>.json (userdata/save-alarm-state.sh).
LOCAL_CONFIG_KEY = f"{HOST_STATE_PREFIX}/agent.local.toml"
ALARM_STATE_PREFIX = f"{HOST_STATE_PREFIX}/alarm-state/"
# S3 Standard-IA bills every object as at least 128 KB; Delta's small log files stay in Standard.
IA_MIN_OBJECT_BYTES = 128 * 1024


class HistoryBucket(Construct):
    """An encrypted, private, TLS-only bucket whose `history/` objects move to Standard-IA after
    `infrequent_access_after_days`; kept on `cdk destroy` unless `retain` is false.

    Attributes: `bucket`, `uri` (what the agent config's [history] uri is set to), `calibration_uri` (its
    [telemetry] calibrations), `host_state_uri` (the host's HOST_STATE_URI). `grant_agent(role)` gives a role
    exactly the history prefix, read access to the calibration prefix, the host's one object and its alarm
    state prefix.
    """

    def __init__(
        self, scope: Construct, id_: str, *, infrequent_access_after_days: int, retain: bool
    ) -> None:
        super().__init__(scope, id_)
        self.bucket = s3.Bucket(
            self,
            "Bucket",
            encryption=s3.BucketEncryption.S3_MANAGED,
            block_public_access=s3.BlockPublicAccess.BLOCK_ALL,
            enforce_ssl=True,
            object_ownership=s3.ObjectOwnership.BUCKET_OWNER_ENFORCED,
            lifecycle_rules=_lifecycle_rules(infrequent_access_after_days),
            # History outlives the instance: by default `cdk destroy` leaves the bucket (docs/deploy.md says
            # how to delete it). With retainHistory=false the stack empties and deletes it.
            removal_policy=RemovalPolicy.RETAIN if retain else RemovalPolicy.DESTROY,
            auto_delete_objects=not retain,
        )
        # CloudFormation types ObjectSizeGreaterThan as a string; CDK writes a number (cfn-lint W9003).
        cfn = self.bucket.node.default_child
        assert isinstance(cfn, s3.CfnBucket)
        cfn.add_property_override(
            "LifecycleConfiguration.Rules.0.ObjectSizeGreaterThan", str(IA_MIN_OBJECT_BYTES)
        )
        self.uri = f"s3://{self.bucket.bucket_name}/{HISTORY_PREFIX}"
        self.calibration_uri = f"s3://{self.bucket.bucket_name}/{CALIBRATION_PREFIX}"
        self.host_state_uri = f"s3://{self.bucket.bucket_name}/{HOST_STATE_PREFIX}"
        Validations.of(self.bucket).acknowledge(
            Acknowledgment(
                id="AwsSolutions-S1",
                reason="Server access logs would need a second bucket and grow with every commit (one every "
                "10 s); the only writer is this stack's host role, whose API calls CloudTrail records.",
            )
        )
        skip_checkov(
            self.bucket,
            {
                "CKV_AWS_18": "Access logging: see the AwsSolutions-S1 acknowledgement (CloudTrail "
                "covers the single writer).",
                "CKV_AWS_21": "Versioning would keep every file Delta compacts and vacuums away forever; "
                "the Delta log itself versions the tables (time travel within the vacuum retention).",
                "CKV_AWS_145": "SSE-S3 encrypts every object; a customer KMS key would add a key policy and "
                "a KMS request per object read or written for no gain in a single-account dev stack.",
            },
        )

    def grant_agent(self, role: iam.IRole) -> None:
        """Read, write and delete under `history/` only, and list only that prefix; read and list the
        calibrations; read and write the host's copy of agent.local.toml, and list only its key; read and
        write the hosts' copies of the alarm state, and list only their prefix."""
        self._grant_history(role)
        self._grant_calibrations(role)
        self._grant_local_config(role)
        self._grant_alarm_state(role)
        self._acknowledge_wildcards(role)

    def _grant_history(self, role: iam.IRole) -> None:
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HistoryObjects",
                actions=["s3:GetObject", "s3:PutObject", "s3:DeleteObject"],
                resources=[self.bucket.arn_for_objects(f"{HISTORY_PREFIX}/*")],
            )
        )
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HistoryList",
                actions=["s3:ListBucket"],
                resources=[self.bucket.bucket_arn],
                conditions={"StringLike": {"s3:prefix": [f"{HISTORY_PREFIX}/*", HISTORY_PREFIX]}},
            )
        )

    def _grant_calibrations(self, role: iam.IRole) -> None:
        # The arms' calibrations: read only (people push them with their own credentials), list that prefix.
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="CalibrationRead",
                actions=["s3:GetObject"],
                resources=[self.bucket.arn_for_objects(f"{CALIBRATION_PREFIX}/*")],
            )
        )
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="CalibrationList",
                actions=["s3:ListBucket"],
                resources=[self.bucket.bucket_arn],
                conditions={"StringLike": {"s3:prefix": [f"{CALIBRATION_PREFIX}/*", CALIBRATION_PREFIX]}},
            )
        )

    def _grant_local_config(self, role: iam.IRole) -> None:
        # The operator's agent.local.toml: that one object, read at a new host's first boot and written when
        # it changes; the listing (of its own key only) tells a missing copy from one the host cannot read.
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HostLocalConfig",
                actions=["s3:GetObject", "s3:PutObject"],
                resources=[self.bucket.arn_for_objects(LOCAL_CONFIG_KEY)],
            )
        )
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HostLocalConfigList",
                actions=["s3:ListBucket"],
                resources=[self.bucket.bucket_arn],
                conditions={"StringEquals": {"s3:prefix": [LOCAL_CONFIG_KEY]}},
            )
        )

    def _grant_alarm_state(self, role: iam.IRole) -> None:
        # Each host writes its own copy under its host id; a new host's first boot lists them and reads the
        # one written last (userdata/install-agent.sh).
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HostAlarmState",
                actions=["s3:GetObject", "s3:PutObject"],
                resources=[self.bucket.arn_for_objects(f"{ALARM_STATE_PREFIX}*")],
            )
        )
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="HostAlarmStateList",
                actions=["s3:ListBucket"],
                resources=[self.bucket.bucket_arn],
                conditions={"StringEquals": {"s3:prefix": [ALARM_STATE_PREFIX]}},
            )
        )

    def _acknowledge_wildcards(self, role: iam.IRole) -> None:
        """cdk-nag's IAM5 on the two prefixes whose keys the agent and the fleet choose."""
        stack = Stack.of(self)
        # An L2 Bucket's default child is the CfnBucket it wraps; the construct tree types it as a construct.
        cfn_bucket = cast(s3.CfnBucket, self.bucket.node.default_child)
        Validations.of(role).acknowledge(
            Acknowledgment(
                id=f"AwsSolutions-IAM5[Resource::<{stack.get_logical_id(cfn_bucket)}.Arn>/"
                f"{CALIBRATION_PREFIX}/*]",
                reason="One object per arm, named for its device id (<device>.json), which the fleet "
                "decides; read only, on the calibration prefix of this stack's own bucket.",
            )
        )
        Validations.of(role).acknowledge(
            Acknowledgment(
                id=f"AwsSolutions-IAM5[Resource::<{stack.get_logical_id(cfn_bucket)}.Arn>/"
                f"{HISTORY_PREFIX}/*]",
                reason="Delta Lake writes a new object per commit (Parquet files, log entries, checkpoints) "
                "under keys it chooses; the wildcard is the history prefix of this stack's own bucket only.",
            )
        )
        Validations.of(role).acknowledge(
            Acknowledgment(
                id=f"AwsSolutions-IAM5[Resource::<{stack.get_logical_id(cfn_bucket)}.Arn>/"
                f"{ALARM_STATE_PREFIX}*]",
                reason="One object per twin host, named for the host id its first boot makes, so that a "
                "host and the one replacing it never write the same key; read and write only, no delete.",
            )
        )


def _lifecycle_rules(infrequent_access_after_days: int) -> list[s3.LifecycleRule]:
    """History objects to Standard-IA, maintenance leases expired, incomplete uploads aborted."""
    return [
        s3.LifecycleRule(
            id="HistoryToInfrequentAccess",
            prefix=f"{HISTORY_PREFIX}/",
            object_size_greater_than=IA_MIN_OBJECT_BYTES,
            transitions=[
                s3.Transition(
                    storage_class=s3.StorageClass.INFREQUENT_ACCESS,
                    transition_after=Duration.days(infrequent_access_after_days),
                )
            ],
        ),
        # One lease object per table and maintenance window (docs/history.md, Maintenance).
        s3.LifecycleRule(
            id="ExpireMaintenanceLeases",
            prefix=f"{HISTORY_PREFIX}/_maintenance/",
            expiration=Duration.days(2),
        ),
        s3.LifecycleRule(
            id="AbortIncompleteUploads", abort_incomplete_multipart_upload_after=Duration.days(1)
        ),
    ]
