"""Where the twin keeps files of its own (the history, the calibration store): a local directory, or
s3://bucket/prefix. One rule for the agent's settings and the commands' options, so that a location one takes
the other does not refuse, and a mistyped one is named rather than taken as something else."""

from __future__ import annotations

import re

# "s3:/bucket/h" or "s3:bucket/h": a slash short of a URI. Taken as a directory, the calibration store made a
# local folder named "s3:" and pushed there; read as a URI, the history asked the host's metadata service for
# credentials before a vague error.
# S3 only: a local folder named "https:x" or "gs:old" is rare, but the user's to name (a review).
_SCHEME_SHORT_OF_SLASHES = re.compile(r"(s3):/?(?!/)", re.IGNORECASE)


def location_problem(location: str) -> str:
    """What is wrong with `location` as a directory or s3://bucket/prefix, to follow it in a message (the
    caller adds an example of its own); "" when nothing is."""
    text = location.strip()
    short = _SCHEME_SHORT_OF_SLASHES.match(text)
    if short and "://" not in text:
        return f"lacks the '//' after '{short.group(1)}:', as in s3://bucket/prefix"
    if "://" in text and not text.startswith(("s3://", "file://")):
        return "is not a directory or s3://bucket/prefix"
    if text.startswith("s3://") and not text.removeprefix("s3://").split("/", 1)[0]:
        return "names no bucket"
    return ""
