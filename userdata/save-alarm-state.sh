#!/usr/bin/env bash
# Saves the agent's servo alarm state on this host (its state file, lib.sh ALARM_STATE: the alarms that are
# acknowledged, latched or active, twin.service.persist) to the stack's bucket under this host's own key, so
# that a change that replaces the instance does not lose them: the next host's first boot adopts the newest
# host's copy (install-agent.sh). Run from the host's scripts (/opt/so101-twin/userdata) by
# so101-twin-alarm-state.service, which a systemd path unit starts whenever the agent writes the file (when
# its kept alarms change, at its start and at its stop), and once by every run of install-agent.sh.
#   save-alarm-state.sh S3_PREFIX   where the hosts keep their copies (s3://<bucket>/host/alarm-state/)
#   ROOT   prefix for the files (tests); AWS_REGION the bucket's region; AGENT_NAME the metrics' Agent;
#   SAVE_EVERY_S   the least time between two uploads (default 30; install-agent.sh gives 0)
# The key is <S3_PREFIX><host id>.json (lib.sh HOST_ID_FILE: the time of this disk's first install, then a
# random part): during a replacement the old host and its successor run side by side, and each keeps its
# own copy, so the old host's last writes cannot overwrite its successor's. The agent may rewrite the file
# every second while alarms flap across a fleet, and each upload starts the AWS CLI (a fraction of a second
# of CPU): after an upload the saver waits SAVE_EVERY_S and uploads again only if the file changed meanwhile,
# so it uploads at most once in that time and still ends with the file as it is (a start asked for while it
# runs merges into this run). Exits 0 when saved or there is nothing to save, 1 when it could not be saved.
# Each run ends with the metric AlarmStateNotSaved (1 or 0), which the stack's alarm of that name watches.
set -Eeuo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG_TAG=save-alarm-state
# shellcheck source=userdata/lib.sh
. "$HERE/lib.sh"

PREFIX="${1:?usage: save-alarm-state.sh s3://<bucket>/host/alarm-state/}"
FILE="${ROOT}${ALARM_STATE}"

not_saved() { saved_metric AlarmStateNotSaved "$1"; }

if [ ! -f "$FILE" ]; then
  log "nothing to save: ${ALARM_STATE} does not exist (the agent writes it at its first check)"
  not_saved 0
  exit 0
fi
if ! host_id="$(cat "${ROOT}${HOST_ID_FILE}" 2>/dev/null)" || [ -z "$host_id" ]; then
  log "not saved: ${HOST_ID_FILE} is missing, which install-agent.sh writes; run it again (a deploy does)"
  not_saved 1
  exit 1
fi
target="${PREFIX%/}/${host_id}.json"
uploaded="$(mktemp "${TMPDIR:-/tmp}/so101-twin-alarm-state.XXXXXX")"
trap 'rm -f "$uploaded"' EXIT
while :; do
  outcome=0
  upload_file "$FILE" "$target" "$uploaded" || outcome=$?
  [ "$outcome" = 0 ] || break
  log "saved ${ALARM_STATE} to ${target}"
  not_saved 0
  sleep "${SAVE_EVERY_S:-30}"
  if cmp -s "$uploaded" "$FILE"; then exit 0; fi
  log "${ALARM_STATE} changed since; saving it again"
done
case "$outcome" in
  1)
    log "not saved: ${ALARM_STATE} could not be uploaded to ${target} (the AWS CLI's error is above), so a" \
      "host that replaces this one would start without its acknowledged and latched servo alarms. Check" \
      "the host role's s3:PutObject under ${PREFIX} and the host's network; the next change of the alarms," \
      "or 'systemctl start so101-twin-alarm-state', saves it"
    not_saved 1
    exit 1
    ;;
  *)
    log "not saved: ${ALARM_STATE} kept changing while it was saved; its next change saves it"
    not_saved 1
    exit 1
    ;;
esac
