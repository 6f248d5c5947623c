"""hostGeneration: the way to a new host in place of a terminated one, through real `cdk synth` and cdk-nag.

A deploy of unchanged settings does nothing for a terminated instance (CloudFormation does not see that it is
gone), so the setting renames what belongs to one host: a new logical id is a resource CloudFormation creates.
At its default the template must be the one deployed stacks already have, or upgrading so101-twin would
replace their hosts.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from stacks.settings import DEFAULT_AMI_SSM_PARAMETER

from .synth import ALL_OPTIONS, Synth

# What the first host's resources have always been called (the template of every deployed stack).
FIRST_HOST = {
    "AWS::EC2::Instance": "HostInstance2C59A3BE",
    "AWS::IAM::InstanceProfile": "HostInstanceInstanceProfile65A03AB8",
    "AWS::CloudFormation::WaitConditionHandle": "HostBootHandleC9726E0B",
    "AWS::CloudFormation::WaitCondition": "HostBootWaitBF7FFDD3",
}


@pytest.fixture(scope="module")
def synth_second_host(synth_factory: Callable[..., Synth]) -> Synth:
    return synth_factory(**ALL_OPTIONS, hostGeneration="2")


def only(synth: Synth, type_: str) -> str:
    (logical_id,) = synth.resources(type_)
    return logical_id


def test_the_first_host_keeps_the_ids_and_fingerprint_deployed_stacks_have(synth_default: Synth) -> None:
    assert {type_: only(synth_default, type_) for type_ in FIRST_HOST} == FIRST_HOST
    fingerprint = synth_default.json["Outputs"]["InstanceFingerprint"]["Value"]
    assert fingerprint == json.dumps(
        {"availabilityZone": "", "image": f"resolve:ssm:{DEFAULT_AMI_SSM_PARAMETER}", "volumeGb": "100"}
    )


def test_a_second_host_is_new_resources_and_everything_follows_it(
    synth_all_options: Synth, synth_second_host: Synth
) -> None:
    first, second = synth_all_options.json, synth_second_host.json
    renamed = {t: (only(synth_all_options, t), only(synth_second_host, t)) for t in FIRST_HOST}
    assert all(old != new for old, new in renamed.values()), renamed
    # Nothing else is added or removed: the bucket, the Elastic IP, the secret and the rest stay.
    olds, news = {old for old, _ in renamed.values()}, {new for _, new in renamed.values()}
    assert set(first["Resources"]) - olds == set(second["Resources"]) - news
    # Whatever named the old ones (the EIP and SSM associations, the alarm, the auto-stop, the outputs, the
    # boot's UserData) names the new ones, as often: no old id is left anywhere.
    before, after = json.dumps(first), json.dumps(second)
    assert [old for old in olds if old in after] == []
    assert [after.count(new) for _, new in renamed.values()] == [
        before.count(old) for old, _ in renamed.values()
    ]


def test_the_second_hosts_boot_signals_its_own_resource_and_wait_condition(synth_second_host: Synth) -> None:
    instance_id = only(synth_second_host, "AWS::EC2::Instance")
    user_data = json.dumps(synth_second_host.json["Resources"][instance_id]["Properties"]["UserData"])
    assert f"SO101_TWIN_RESOURCE='{instance_id}'" in user_data
    handle = only(synth_second_host, "AWS::CloudFormation::WaitConditionHandle")
    assert json.dumps({"Ref": handle}) in user_data
    wait = synth_second_host.one("AWS::CloudFormation::WaitCondition")
    assert wait["Properties"]["Handle"] == {"Ref": handle}
    # Its CreationPolicy is the one the first host had: the deploy waits for the new boot's signal.
    assert synth_second_host.json["Resources"][instance_id]["CreationPolicy"]["ResourceSignal"]["Count"] == 1
    tags = synth_second_host.json["Resources"][instance_id]["Properties"]["Tags"]
    assert {"Key": "Name", "Value": "So101TwinStack/Host/InstanceGen2"} in tags


def test_the_second_hosts_fingerprint_names_its_generation(synth_second_host: Synth) -> None:
    fingerprint = json.loads(synth_second_host.json["Outputs"]["InstanceFingerprint"]["Value"])
    assert fingerprint["hostGeneration"] == "2"
