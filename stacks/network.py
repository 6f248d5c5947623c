"""One-AZ public network for the twin host: no NAT, flow logs on, DCV reachable from the client only."""

from __future__ import annotations

from aws_cdk import Acknowledgment, RemovalPolicy, Stack, Validations
from aws_cdk import aws_ec2 as ec2
from aws_cdk import aws_logs as logs
from constructs import Construct

from stacks.skips import LAMBDA_DEPLOY_TIME_ONLY, LOG_GROUP_KMS, skip_checkov

DCV_PORT = 8443
VPC_CIDR = "10.0.0.0/16"


class TwinNetwork(Construct):
    """VPC 10.0.0.0/16 with one public subnet and the host's security group.

    The subnet does not hand out public IPs: the host's only address is its Elastic IP, so the DCV
    URL never changes and nothing in the subnet is reachable by accident.
    """

    def __init__(
        self,
        scope: Construct,
        id_: str,
        *,
        client_cidr: str | None,
        allow_any_client: bool,
        availability_zone: str | None,
    ) -> None:
        super().__init__(scope, id_)
        self.vpc = self._vpc(availability_zone)
        self.flow_log_group = self._flow_log()

        # Flag restrictDefaultSecurityGroup adds a deploy-time Lambda (stack-level singleton) that strips
        # the default security group's rules.
        provider = Stack.of(self).node.try_find_child("Custom::VpcRestrictDefaultSGCustomResourceProvider")
        if provider is not None:
            skip_checkov(provider.node.find_child("Handler"), LAMBDA_DEPLOY_TIME_ONLY)

        self.security_group = self._security_group(client_cidr, allow_any_client)

    def _vpc(self, availability_zone: str | None) -> ec2.Vpc:
        """The VPC: one public subnet in one AZ (the given one, else any), no NAT."""
        zone_options: dict = (
            {"availability_zones": [availability_zone]} if availability_zone else {"max_azs": 1}
        )
        return ec2.Vpc(
            self,
            "Vpc",
            ip_addresses=ec2.IpAddresses.cidr(VPC_CIDR),
            nat_gateways=0,
            subnet_configuration=[
                ec2.SubnetConfiguration(
                    name="Public",
                    subnet_type=ec2.SubnetType.PUBLIC,
                    cidr_mask=24,
                    map_public_ip_on_launch=False,
                )
            ],
            **zone_options,
        )

    def _flow_log(self) -> logs.LogGroup:
        """The VPC's flow log of all traffic, and the log group it goes to."""
        flow_log_group = logs.LogGroup(
            self,
            "FlowLogGroup",
            retention=logs.RetentionDays.ONE_YEAR,
            removal_policy=RemovalPolicy.DESTROY,
        )
        skip_checkov(flow_log_group, {"CKV_AWS_158": LOG_GROUP_KMS})
        self.vpc.add_flow_log(
            "FlowLog",
            destination=ec2.FlowLogDestination.to_cloud_watch_logs(flow_log_group),
            traffic_type=ec2.FlowLogTrafficType.ALL,
        )
        return flow_log_group

    def _security_group(self, client_cidr: str | None, allow_any_client: bool) -> ec2.SecurityGroup:
        """The host's security group: DCV in from the client CIDR, HTTPS and HTTP out."""
        security_group = ec2.SecurityGroup(
            self,
            "HostSecurityGroup",
            vpc=self.vpc,
            description="so101-twin host: DCV from the client CIDR only",
            # Outbound is only what the host uses: HTTPS (S3 assets, DCV licence, IoT Core, SSM, Secrets
            # Manager, pip, the DCV download) and HTTP (the Ubuntu apt mirrors serve plain HTTP, signed).
            allow_all_outbound=False,
        )
        security_group.add_egress_rule(ec2.Peer.any_ipv4(), ec2.Port.tcp(443), "HTTPS to AWS APIs and PyPI")
        security_group.add_egress_rule(
            ec2.Peer.any_ipv4(), ec2.Port.tcp(80), "HTTP to the Ubuntu apt mirrors"
        )
        # IPv4 only: the settings refuse an IPv6 client because nothing here has an IPv6 address. Without a
        # client range (a synth for `cdk destroy`, which the app's error annotation keeps from deploying)
        # nothing is admitted.
        if client_cidr is not None:
            peer = ec2.Peer.ipv4(client_cidr)
            security_group.add_ingress_rule(
                peer, ec2.Port.tcp(DCV_PORT), "DCV web client and native client (HTTPS/WebSocket)"
            )
            security_group.add_ingress_rule(
                peer, ec2.Port.udp(DCV_PORT), "DCV QUIC transport (native client)"
            )
        if allow_any_client:
            # Settings refuse an open CIDR unless the deployer passed allowAnyClient=true on purpose.
            Validations.of(security_group).acknowledge(
                Acknowledgment(
                    id="AwsSolutions-EC23",
                    reason="The deployer explicitly passed -c allowAnyClient=true (e.g. roaming between "
                    "networks); DCV still requires the generated password, and no other port is open.",
                )
            )
        return security_group
