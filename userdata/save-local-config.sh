#!/usr/bin/env bash
# Saves the operator's own agent settings on this host (/etc/so101-twin/agent.local.toml) to the stack's
# bucket, so that a change that replaces the instance does not lose them: the next host's first boot puts
# them back (install-agent.sh). Run from the host's scripts (/opt/so101-twin/userdata) by
# so101-twin-local-config.service, which a systemd path unit starts whenever the file changes, and once by
# every run of install-agent.sh.
#   save-local-config.sh S3_URI   where to keep the file (s3://<bucket>/host/agent.local.toml)
#   ROOT   prefix for the file (tests); AWS_REGION the bucket's region; AGENT_NAME the metrics' Agent
# A file that is still the placeholder install-agent.sh writes when the saved copy could not be read is not
# saved: it would replace the settings it stands in for; nor is one the agent could not start with (checked
# by the installed `twin config check` on top of the generated config). Exits 0 when saved or there is
# nothing to save, 1 when it could not be saved (lib.sh, upload_file; the unit's journal has the AWS CLI's
# error) or is not valid. Each run ends with the metric LocalConfigNotSaved (lib.sh, emit_host_metrics): 1
# while the bucket does not hold this host's settings as they are (the upload failed, the file is that
# placeholder or not valid), else 0; the stack's alarm of that name pages on 1 and clears on the next 0.
set -Eeuo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG_TAG=save-local-config
# shellcheck source=userdata/lib.sh
. "$HERE/lib.sh"

TARGET="${1:?usage: save-local-config.sh s3://<bucket>/host/agent.local.toml}"
FILE="${ROOT}${LOCAL_CONFIG}"

not_saved() { saved_metric LocalConfigNotSaved "$1"; }

if [ ! -f "$FILE" ]; then
  log "nothing to save: ${LOCAL_CONFIG} does not exist"
  not_saved 0
  exit 0
fi
if grep -qxF "$LOCAL_CONFIG_PLACEHOLDER" "$FILE"; then
  log "not saved: ${LOCAL_CONFIG} is the placeholder for settings that could not be read from ${TARGET};" \
    "the next deploy tries again (or delete its line '${LOCAL_CONFIG_PLACEHOLDER}'" \
    "to keep this file as it is)"
  not_saved 1
  exit 0
fi
# A file the agent cannot start with (a typo in an edit) would replace the last good copy in a bucket that
# keeps no versions: a host that replaced this one would start with no agent. Checked as the agent reads it,
# on a copy that is then uploaded as checked: a change made meanwhile (the path unit does not start this
# again for it) is checked in a round of its own, not uploaded unchecked.
twin="${ROOT}${VENV:-/opt/so101-twin/venv}/bin/twin"
copy="$(mktemp "${TMPDIR:-/tmp}/so101-twin-local-config.XXXXXX")"
trap 'rm -f "$copy"' EXIT
for round in 1 2 3 4 5; do
  outcome=1
  cp "$FILE" "$copy" || break
  checked=0
  problem="$("$twin" config check "${ROOT}${CONFIG}" "$copy" 2>&1)" || checked=$?
  problem="${problem//"$copy"/"$LOCAL_CONFIG"}"  # the agent names the file it read: the operator's
  if [ "$checked" = 2 ]; then  # twin config check's answer for a config the agent refuses
    log "not saved: ${LOCAL_CONFIG} is not a config the agent can start with: ${problem}." \
      "The copy at ${TARGET} keeps the settings saved last. Correct the file ('twin config check" \
      "${CONFIG} ${LOCAL_CONFIG}' says what is wrong); its next change saves it"
    not_saved 1
    exit 1
  elif [ "$checked" != 0 ]; then
    # The agent's own venv did not run (a deploy replacing it, a broken install): nothing is known of the
    # file, and that is not the operator's typo.
    log "not saved: ${LOCAL_CONFIG} could not be checked, ${twin#"${ROOT}"} failed (exit ${checked}):" \
      "${problem}. The copy at ${TARGET} keeps the settings saved last; once the agent's venv works" \
      "(sudo systemctl status so101-twin-agent), 'systemctl start so101-twin-local-config' saves it"
    not_saved 1
    exit 1
  fi
  outcome=0
  upload_file "$copy" "$TARGET" || outcome=$?
  [ "$outcome" = 0 ] || break
  cmp -s "$copy" "$FILE" && break
  outcome=2
  [ "$round" = 5 ] || log "${LOCAL_CONFIG} changed while it was saved; saving it again"
done
case "$outcome" in
  0)
    log "saved ${LOCAL_CONFIG} to ${TARGET}"
    not_saved 0
    ;;
  1)
    log "not saved: ${LOCAL_CONFIG} could not be uploaded to ${TARGET} (the AWS CLI's error is above), so" \
      "a host that replaces this one would start without it. Check the host role's s3:PutObject on that" \
      "key and the host's network; its next change, or 'systemctl start so101-twin-local-config', saves it"
    not_saved 1
    exit 1
    ;;
  *)
    log "not saved: ${LOCAL_CONFIG} kept changing while it was saved; the copy at ${TARGET} may be behind:" \
      "its next change saves it"
    not_saved 1
    exit 1
    ;;
esac
