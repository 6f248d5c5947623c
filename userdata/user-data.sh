#!/bin/bash
# EC2 UserData of the so101-twin host, rendered by stacks/twin_host.py (it fills in the placeholders).
#
# Its text names only things that never change for a stack (region, stack, resource ids, the name of the
# deployment parameter), so a deploy that changes settings or agent code leaves the UserData alone and the
# instance is neither stopped nor replaced; the current settings and asset locations are read from the SSM
# parameter. The same text runs twice in a host's life:
#   first boot (cloud-init):                 SO101_TWIN_MODE unset -> "boot", signals CloudFormation
#   in-place update (SSM State Manager, see userdata/update.sh): SO101_TWIN_MODE=update
# No secret appears here: UserData is readable through IMDS and DescribeInstanceAttribute.
set -Eeuo pipefail

ROOT="${ROOT:-}" # the tests run this against a temporary root; empty on the host
export SO101_TWIN_REGION='@@REGION@@'
export SO101_TWIN_STACK='@@STACK_NAME@@'
export SO101_TWIN_RESOURCE='@@RESOURCE@@'
export SO101_TWIN_PARAMETER='@@PARAMETER@@'
export SO101_TWIN_HANDLE='@@HANDLE_URL@@'
export SO101_TWIN_MODE="${SO101_TWIN_MODE:-boot}"
EXPECTED_VERSION="${SO101_TWIN_EXPECTED_VERSION:-}"
OPT="$ROOT/opt/so101-twin"
LOG="$ROOT/var/log/so101-twin-bootstrap.log"

mkdir -p "$ROOT/var/log" "$ROOT/etc/so101-twin" "$OPT" "$ROOT/var/lib/so101-twin"
# One log from the first line: the file the CloudWatch agent ships (bootstrap.sh sets that up first and
# it reads the file from its beginning), also the run's own output (cloud-init, SSM).
exec > >(tee -a "$LOG") 2>&1
export SO101_TWIN_LOGGING=1
echo "so101-twin user-data: $SO101_TWIN_MODE start $(date -Is)"

# Before bootstrap.sh is here, a failure is reported from this script (bootstrap.sh reports its own).
step=fetch
fail() {
  local rc=$? reason instance tail_text
  trap - ERR
  [ "$BASHPID" = "$$" ] || exit "$rc"
  echo "so101-twin user-data: step $step FAILED (exit $rc)"
  [ "$SO101_TWIN_MODE" = boot ] || exit "$rc"
  sleep 1 # let tee write the line above before it is quoted
  tail_text="$(tail -n 12 "$LOG")"
  [ "${#tail_text}" -le 1200 ] || tail_text="...${tail_text: -1200}"
  reason="step $step failed (exit $rc); last log lines: $tail_text"
  instance="$(cat "$ROOT/var/lib/cloud/data/instance-id" 2>/dev/null || echo unknown)"
  # The wait condition carries the reason into the `cdk deploy` output (SignalResource takes none).
  curl -fsS --max-time 30 --retry 3 -X PUT -H 'Content-Type:' --data-binary @- "$SO101_TWIN_HANDLE" <<JSON || true
$(python3 -c 'import json, sys; print(json.dumps({"Status": "FAILURE", "Reason": sys.argv[1], "UniqueId": sys.argv[2], "Data": ""}))' "$reason" "$instance")
JSON
  aws cloudformation signal-resource --region "$SO101_TWIN_REGION" --stack-name "$SO101_TWIN_STACK" \
    --logical-resource-id "$SO101_TWIN_RESOURCE" --unique-id "$instance-$step" --status FAILURE \
    --cli-connect-timeout 10 --cli-read-timeout 60 || true
  exit "$rc"
}
trap fail ERR

# Only one run at a time: an update that arrives while another runs waits for it.
exec 9>"$ROOT/var/lib/so101-twin/run.lock"
flock 9

# The AWS CLI ships with the DLAMI; other Ubuntu AMIs get it from the snap store.
# A fresh instance's snapd may still be seeding: an install before it is done fails "too early for operation".
if ! command -v aws >/dev/null 2>&1; then
  timeout 600 snap wait system seed.loaded
  timeout 600 snap install aws-cli --classic
fi

# The deployment parameter: asset locations, settings and their version. An update must see the version
# the association was created for; Parameter Store is read-after-write consistent only eventually.
read_deployment() {
  aws ssm get-parameter --region "$SO101_TWIN_REGION" --name "$SO101_TWIN_PARAMETER" \
    --query Parameter.Value --output text --cli-connect-timeout 10 --cli-read-timeout 60 \
    >"$ROOT/etc/so101-twin/deployment.env.new" || return 1
  [ -z "$EXPECTED_VERSION" ] ||
    [ "$(sed -n 's/^DEPLOYMENT_VERSION=//p' "$ROOT/etc/so101-twin/deployment.env.new")" = "$EXPECTED_VERSION" ]
}
wait_deployment() {
  local attempt
  for attempt in $(seq 1 30); do
    if read_deployment; then return 0; fi
    echo "deployment parameter: attempt $attempt not ready (want version ${EXPECTED_VERSION:-any}), retrying in 10 s"
    sleep 10
  done
  return 1
}
wait_deployment
mv -f "$ROOT/etc/so101-twin/deployment.env.new" "$ROOT/etc/so101-twin/deployment.env"
AGENT_URL="$(sed -n 's/^AGENT_URL=//p' "$ROOT/etc/so101-twin/deployment.env")"
SCRIPTS_URL="$(sed -n 's/^SCRIPTS_URL=//p' "$ROOT/etc/so101-twin/deployment.env")"

# IAM changes made in the same deploy take seconds to reach S3, so each download retries (30 tries, each
# bounded by the CLI's time limits).
fetch() {
  local attempt
  for attempt in $(seq 1 30); do
    if aws s3 cp --only-show-errors --region "$SO101_TWIN_REGION" --cli-connect-timeout 10 \
      --cli-read-timeout 60 "$1" "$2"; then return 0; fi
    echo "fetch $1: attempt $attempt failed, retrying in 10 s"
    sleep 10
  done
  return 1
}
fetch "$AGENT_URL" "$OPT/agent-src.zip"
fetch "$SCRIPTS_URL" "$OPT/userdata.zip"
# Unpack next to the old copies, then swap by rename: a running viewer supervisor keeps its open file.
rm -rf "$OPT/agent-src.new" "$OPT/userdata.new"
python3 -m zipfile -e "$OPT/agent-src.zip" "$OPT/agent-src.new"
python3 -m zipfile -e "$OPT/userdata.zip" "$OPT/userdata.new"
rm -rf "$OPT/agent-src" "$OPT/userdata"
mv "$OPT/agent-src.new" "$OPT/agent-src"
mv "$OPT/userdata.new" "$OPT/userdata"

step=bootstrap
trap - ERR
exec bash "$OPT/userdata/bootstrap.sh" "$ROOT/etc/so101-twin/deployment.env"
