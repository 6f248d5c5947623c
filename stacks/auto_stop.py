"""Optional scheduled stop of the host (EventBridge Scheduler), so a forgotten GPU does not run all night."""

from __future__ import annotations

from aws_cdk import Stack
from aws_cdk import aws_iam as iam
from aws_cdk import aws_scheduler as scheduler
from constructs import Construct


class AutoStop(Construct):
    """A schedule that calls ec2:StopInstances on the one instance, with a role that can do nothing else."""

    def __init__(self, scope: Construct, id_: str, *, instance_id: str, cron: str, timezone: str) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)
        self.role = iam.Role(
            self,
            "SchedulerRole",
            assumed_by=iam.ServicePrincipal(
                "scheduler.amazonaws.com", conditions={"StringEquals": {"aws:SourceAccount": stack.account}}
            ),
            description="so101-twin auto-stop: may stop the twin host and nothing else",
        )
        instance_arn = stack.format_arn(service="ec2", resource="instance", resource_name=instance_id)
        self.role.add_to_policy(
            iam.PolicyStatement(sid="StopTwinHost", actions=["ec2:StopInstances"], resources=[instance_arn])
        )
        self.schedule = scheduler.CfnSchedule(
            self,
            "Schedule",
            description="Stop the so101-twin host on a schedule (autoStopCron)",
            schedule_expression=cron,
            schedule_expression_timezone=timezone,
            flexible_time_window=scheduler.CfnSchedule.FlexibleTimeWindowProperty(mode="OFF"),
            target=scheduler.CfnSchedule.TargetProperty(
                # Scheduler's universal target calls the EC2 API directly: no Lambda to maintain.
                arn=f"arn:{stack.partition}:scheduler:::aws-sdk:ec2:stopInstances",
                role_arn=self.role.role_arn,
                input=stack.to_json_string({"InstanceIds": [instance_id]}),
            ),
        )
