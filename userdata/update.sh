#!/bin/sh
# In-place update of the so101-twin host. The stack's SSM State Manager association runs these lines
# (rendered by stacks/twin_host.py) whenever a deploy changes the agent code or the settings: its
# parameters carry the deployment version, and State Manager applies an association again when its
# parameters change. They re-run the host's own UserData, which never changes, in update mode: it reads
# the deployment parameter (waiting until it shows this version), fetches the new assets and re-runs the
# idempotent bootstrap, which changes only what differs and verifies the host like the first boot did.
# POSIX sh: AWS-RunShellScript runs commands with sh.
set -eu
ROOT="${ROOT:-}"
IMDS="${IMDS:-http://169.254.169.254}"
token="$(curl -fsS --max-time 10 --retry 3 -X PUT -H 'X-aws-ec2-metadata-token-ttl-seconds: 300' \
  "$IMDS/latest/api/token")"
mkdir -p "$ROOT/run/so101-twin"
curl -fsS --max-time 10 --retry 3 -H "X-aws-ec2-metadata-token: $token" -o "$ROOT/run/so101-twin/user-data.sh" \
  "$IMDS/latest/user-data"
export SO101_TWIN_MODE=update
export SO101_TWIN_EXPECTED_VERSION='@@VERSION@@'
exec bash "$ROOT/run/so101-twin/user-data.sh"
