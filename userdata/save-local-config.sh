#!/usr/bin/env bash
# Saves the operator's own agent settings on this host (/etc/so101-twin/agent.local.toml) to the stack's
# bucket, so that a change that replaces the instance does not lose them: the next host's first boot puts
# them back (install-agent.sh). Run from the host's scripts (/opt/so101-twin/userdata) by
# so101-twin-local-config.service, which a systemd path unit starts whenever the file changes, and once by
# every run of install-agent.sh.
#   save-local-config.sh S3_URI   where to keep the file (s3://<bucket>/host/agent.local.toml)
#   ROOT   prefix for the file (tests); AWS_REGION the bucket's region
# A file that is still the placeholder install-agent.sh writes when the saved copy could not be read is not
# saved: it would replace the settings it stands in for. Exits 0 when there is nothing to save, 1 when the
# upload failed (the unit's journal has the AWS CLI's error).
set -Eeuo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG_TAG=save-local-config
# shellcheck source=userdata/lib.sh
. "$HERE/lib.sh"

TARGET="${1:?usage: save-local-config.sh s3://<bucket>/host/agent.local.toml}"
FILE="${ROOT}${LOCAL_CONFIG}"

if [ ! -f "$FILE" ]; then
  log "nothing to save: ${LOCAL_CONFIG} does not exist"
  exit 0
fi
if grep -qxF "$LOCAL_CONFIG_PLACEHOLDER" "$FILE"; then
  log "not saved: ${LOCAL_CONFIG} is the placeholder for settings that could not be read from ${TARGET};" \
    "the next deploy tries again (or delete its line '${LOCAL_CONFIG_PLACEHOLDER}'" \
    "to keep this file as it is)"
  exit 0
fi
region=()
[ -z "${AWS_REGION:-}" ] || region=(--region "$AWS_REGION")
# What is uploaded is a copy taken first, and the file is compared with it afterwards: systemd does not start
# this unit again for a change made while it runs (the path unit's start merges into the running job), so a
# second save during the upload is caught here and uploaded in turn.
copy="$(mktemp "${TMPDIR:-/tmp}/so101-twin-local-config.XXXXXX")"
trap 'rm -f "$copy"' EXIT
for _ in 1 2 3 4 5; do
  cp "$FILE" "$copy"
  aws s3 cp "${AWS_LIMITS[@]}" "${region[@]}" --only-show-errors "$copy" "$TARGET"
  if cmp -s "$copy" "$FILE"; then
    log "saved ${LOCAL_CONFIG} to ${TARGET}"
    exit 0
  fi
  log "${LOCAL_CONFIG} changed while it was saved; saving it again"
done
log "${LOCAL_CONFIG} kept changing while it was saved; the copy at ${TARGET} may be behind:" \
  "its next change saves it"
exit 1
