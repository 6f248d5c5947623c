"""IAM's size quotas on a role's policies, checked on a synthesized template: a stand-in for IAM, which
refuses a policy over them at deploy time, long after synth (docs/deploy.md, "The IAM role's size").

IAM counts a policy's characters without whitespace: at most 10,240 for all of a role's inline policies
together, 6,144 for each managed policy, and at most 10 managed policies attached to a role by default.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any

INLINE_CHARS_PER_ROLE = 10_240
MANAGED_POLICY_CHARS = 6_144
MANAGED_POLICIES_PER_ROLE = 10

# The longest values a deploy could put in an ARN: every token is rendered at its worst case, so a template
# that fits here fits in every partition, region and account.
_PSEUDO = {"AWS::Partition": "aws-us-gov", "AWS::Region": "ap-southeast-4", "AWS::AccountId": "123456789012"}
# What a reference to another resource (a log group's or a bucket's ARN, a topic's) renders as, at most.
_RESOURCE_ARN = "x" * 200


def render(value: Any) -> Any:
    """A policy document with its intrinsic functions rendered at their longest (Ref, GetAtt, Join)."""
    if isinstance(value, list):
        return [render(v) for v in value]
    if not isinstance(value, dict):
        return value
    if set(value) == {"Ref"}:
        return _PSEUDO.get(value["Ref"], _RESOURCE_ARN)
    if set(value) == {"Fn::GetAtt"}:
        return _RESOURCE_ARN
    if set(value) == {"Fn::Join"}:
        separator, parts = value["Fn::Join"]
        return separator.join(str(render(p)) for p in parts)
    if set(value) == {"Fn::Sub"}:
        text, names = value["Fn::Sub"] if isinstance(value["Fn::Sub"], list) else (value["Fn::Sub"], {})
        return re.sub(r"\$\{([^}]+)\}", lambda m: str(render(names.get(m[1], {"Ref": m[1]}))), text)
    unknown = [k for k in value if k.startswith("Fn::")]
    assert not unknown, f"render() does not know {unknown}: teach it before trusting its sizes"
    return {k: render(v) for k, v in value.items()}


def chars(document: Any) -> int:
    """A policy's size as IAM counts it: rendered, no whitespace."""
    return len(json.dumps(render(document), separators=(",", ":")))


@dataclass(frozen=True)
class RoleSize:
    inline_chars: int
    managed_chars: list[int]

    def problems(self) -> list[str]:
        found = []
        if self.inline_chars > INLINE_CHARS_PER_ROLE:
            found.append(f"inline policies {self.inline_chars} > {INLINE_CHARS_PER_ROLE} characters")
        found += [
            f"managed policy {n} of {c} > {MANAGED_POLICY_CHARS} characters"
            for n, c in enumerate(self.managed_chars)
            if c > MANAGED_POLICY_CHARS
        ]
        if len(self.managed_chars) > MANAGED_POLICIES_PER_ROLE:
            found.append(f"{len(self.managed_chars)} managed policies > {MANAGED_POLICIES_PER_ROLE}")
        return found


def role_size(template: dict[str, Any], role: str) -> RoleSize:
    """The sizes of every policy of the role with logical id `role`: inline ones (AWS::IAM::Policy naming
    it in Roles) and managed ones (AWS::IAM::ManagedPolicy naming it, or in its ManagedPolicyArns)."""
    resources = template["Resources"]
    inline, managed = 0, []
    for resource in resources.values():
        roles = resource.get("Properties", {}).get("Roles", [])
        if {"Ref": role} not in roles or "PolicyDocument" not in resource["Properties"]:
            continue  # not a policy of this role (an instance profile names roles too)
        size = chars(resource["Properties"]["PolicyDocument"])
        if resource["Type"] == "AWS::IAM::Policy":
            inline += size
        elif resource["Type"] == "AWS::IAM::ManagedPolicy":
            managed.append(size)
    properties = resources[role]["Properties"]
    inline += sum(chars(p["PolicyDocument"]) for p in properties.get("Policies", []))
    # AWS managed policies attached by ARN count against the role's ten too (their size is AWS's).
    managed += [0 for _ in properties.get("ManagedPolicyArns", [])]
    return RoleSize(inline, managed)
