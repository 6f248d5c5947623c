"""The AWS region a command uses when none is set, standard library only.

boto3 reads `AWS_DEFAULT_REGION` and the profile's config file, but not `AWS_REGION` (botocore 1.44's
configprovider maps the region to `AWS_DEFAULT_REGION` alone), while the AWS CLI v2, the CDK CLI and AWS's
other SDKs read `AWS_REGION` first. Our docs tell people to set `AWS_REGION`, as AWS's own guides do, so every
boto3 client and session the twin makes takes its region from `region_or_env`: with `AWS_REGION` set and no
region given, a command works as the AWS CLI would in the same shell.
"""

from __future__ import annotations

import os


def region_or_env(region: str | None = None) -> str | None:
    """`region` when set, else `AWS_REGION` when set, else None (boto3 then reads `AWS_DEFAULT_REGION` and
    the profile's config): the AWS CLI's order."""
    if region:
        return region
    return os.environ.get("AWS_REGION", "").strip() or None


def missing_profile_hint(exc: BaseException) -> str:
    """What to do about botocore's ProfileNotFound, whose own text names neither AWS_PROFILE nor a fix.

    The twin never passes a profile name to boto3, so the missing profile is always AWS_PROFILE's (a typo, or
    the docs' `my-profile` typed as it stands); without this, every AWS command stopped with a traceback."""
    return (
        f"{exc}: AWS_PROFILE names a profile that is not in the AWS config; set it to one that "
        "`aws configure list-profiles` lists, create it (`aws configure --profile NAME` or "
        "`aws configure sso`), or unset AWS_PROFILE"
    )
