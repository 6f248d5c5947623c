# shellcheck shell=bash
# Helpers shared by bootstrap.sh, install-agent.sh and host-check.sh (sourced, never run).
#
# ROOT is the install prefix: empty on the host, a temporary directory in the tests. Every path a script
# touches is written "${ROOT}/..."; every system tool is called by name through PATH, so the tests put
# stand-ins first on PATH and the very same lines run in both places.

ROOT="${ROOT:-}"
ROOT="${ROOT%/}"
CHANGED="${CHANGED:-0}"

log() { echo "${LOG_TAG:-so101-twin}: $(date -Is) $*"; }

# The host scripts' own metric lines (EMF), which the CloudWatch agent ships (bootstrap.sh, step logs) and the
# stack's alarms watch (stacks/monitoring.py).
HOST_EMF_FILE=/var/log/so101-twin-host-emf.log

# emit_host_metrics VENV NAME=COUNT...: one EMF line with these counts (namespace SO101Twin, dimension Agent =
# AGENT_NAME), written by the agent's own EMF code in VENV (agents/twin/output/emf.py), so the host's lines
# and the agent's cannot differ in form.
emit_host_metrics() {
  local venv="$1"
  shift
  mkdir -p "$(dirname "${ROOT}${HOST_EMF_FILE}")"
  "${ROOT}${venv}/bin/python" - "${AGENT_NAME:-so101-twin}" "$@" >>"${ROOT}${HOST_EMF_FILE}" <<'PY'
import json, sys, time

from twin.output.emf import AGENT_DIMENSION, Metric, emf_document

agent, pairs = sys.argv[1], [arg.split("=", 1) for arg in sys.argv[2:]]
metrics = [Metric(name, float(count), "Count") for name, count in pairs]
document = emf_document(metrics, {AGENT_DIMENSION: agent}, int(time.time() * 1000))
print(json.dumps(document, separators=(",", ":")))
PY
}

# retry CMD...: three tries, 10 and 20 s apart (mirrors and CDNs have bad minutes, not bad hours). Each
# command bounds its own time (curl --max-time, apt's timeouts), so a retried step is bounded too.
retry() {
  local n
  for n in 1 2 3; do
    if "$@"; then return 0; fi
    [ "$n" = 3 ] && break
    log "retry $n/2 in $((n * 10)) s: $*"
    sleep $((n * 10))
  done
  log "gave up after 3 tries: $*"
  return 1
}

# wait_for TRIES INTERVAL_S WHAT CMD...: poll until CMD succeeds; bounded by TRIES, never by a clock.
wait_for() {
  local tries="$1" interval="$2" what="$3" n
  shift 3
  for ((n = 1; n <= tries; n++)); do
    if "$@"; then return 0; fi
    sleep "$interval"
  done
  log "timed out after $((tries * interval)) s waiting for $what"
  return 1
}

# download URL OUT [MAX_S]: HTTPS only, a time limit per attempt (default 120 s) and curl's own retries for
# any transient error, so one call is bounded by about 4 x MAX_S.
download() {
  curl -fsSL --proto '=https' --tlsv1.2 --connect-timeout 15 --max-time "${3:-120}" \
    --retry 3 --retry-delay 5 --retry-all-errors -o "$2" "$1"
}

# write_file PATH MODE: content on stdin; PATH is below ROOT. Replaced (atomically, by rename, so a
# running reader never sees half a file) only when the content differs; sets CHANGED=1 when it did.
write_file() {
  local path="${ROOT}$1" mode="$2" tmp
  mkdir -p "$(dirname "$path")"
  tmp="$(mktemp "$(dirname "$path")/.so101-twin.XXXXXX")"
  cat >"$tmp"
  if [ -f "$path" ] && cmp -s "$tmp" "$path"; then
    rm -f "$tmp"
    return 0
  fi
  chmod "$mode" "$tmp"
  mv -f "$tmp" "$path"
  log "wrote $1"
  CHANGED=1
}

# installed PKG: dpkg says the package is installed. Output is captured whole, never piped into a reader
# that stops early (under pipefail that kills the writer with SIGPIPE and fails the caller).
installed() {
  local status
  status="$(dpkg-query -W -f='${Status}' "$1" 2>/dev/null)" || return 1
  [ "$status" = "install ok installed" ]
}

# The operator's own agent settings on the host (install-agent.sh creates it once and never writes it again;
# save-local-config.sh keeps a copy in the stack's bucket), and the line that marks the placeholder written
# when that copy could not be read at install: such a file is not saved, and the next install tries again.
# shellcheck disable=SC2034 # used by the scripts that source this file
LOCAL_CONFIG=/etc/so101-twin/agent.local.toml
# shellcheck disable=SC2034
LOCAL_CONFIG_PLACEHOLDER="# so101-twin: placeholder, the saved settings could not be read; the next deploy tries again"

# The agent's servo alarm state file (its [twin] state_file: twin.service.persist) and this disk's host id,
# made at its first install: the alarm state's copy in the stack's bucket is kept under that id
# (save-alarm-state.sh), and a host that replaces this one adopts the newest host's (install-agent.sh).
# shellcheck disable=SC2034
ALARM_STATE=/var/lib/so101-twin-agent/state.json
# shellcheck disable=SC2034
HOST_ID_FILE=/var/lib/so101-twin/host-id
# The agent's events, read back at its next start (its [twin] events_file: twin.service.event_journal); kept
# on this disk only: a new disk's Events page begins with its first start.
# shellcheck disable=SC2034
EVENTS_FILE=/var/lib/so101-twin-agent/events.jsonl

# The AWS CLI's own time limits (it retries by itself), so no call hangs a boot.
# shellcheck disable=SC2034 # used by the scripts that source this file
AWS_LIMITS=(--cli-connect-timeout 10 --cli-read-timeout 60)

# saved_metric NAME 0|1: a saver's outcome as its metric, written with the agent's venv; a metric line that
# cannot be written is logged and changes nothing the saver did.
saved_metric() {
  emit_host_metrics "${VENV:-/opt/so101-twin/venv}" "$1=$2" || log "could not write the $1 metric line"
}

# upload_file FILE S3_URI [KEEP]: a copy of FILE taken first is uploaded, and FILE is compared with it
# afterwards: systemd does not start a path unit's service again for a change made while it runs (the start
# merges into the running job), so a change during the upload is caught here and uploaded in turn (up to 5
# uploads). 0 saved as it is (the copy uploaded left at KEEP when given); 1 an upload failed (the AWS CLI's
# error on stderr); 2 FILE kept changing.
upload_file() {
  local file="$1" target="$2" keep="${3:-}" copy region=() n
  [ -z "${AWS_REGION:-}" ] || region=(--region "$AWS_REGION")
  copy="$(mktemp "${TMPDIR:-/tmp}/so101-twin-upload.XXXXXX")"
  for n in 1 2 3 4 5; do
    if ! cp "$file" "$copy"; then
      rm -f "$copy"
      return 1
    fi
    if ! aws s3 cp "${AWS_LIMITS[@]}" "${region[@]}" --only-show-errors "$copy" "$target"; then
      rm -f "$copy"
      return 1
    fi
    if cmp -s "$copy" "$file"; then
      if [ -n "$keep" ]; then mv -f "$copy" "$keep"; else rm -f "$copy"; fi
      return 0
    fi
    [ "$n" = 5 ] || log "${file#"${ROOT}"} changed while it was saved; saving it again"
  done
  rm -f "$copy"
  return 2
}

# apt's own limits: the boot holds automatic updates still and checks the dpkg lock first (bootstrap.sh,
# step apt), so a lock wait here is short; downloads time out and are retried instead of hanging.
APT_OPTS=(-o DPkg::Lock::Timeout=120 -o Acquire::Retries=3 -o Acquire::http::Timeout=30
  -o Acquire::https::Timeout=30)

# apt_install [--recommends] PKG...: the packages not installed yet; without recommends unless asked.
apt_install() {
  local missing=() pkg recommends=--no-install-recommends
  if [ "${1:-}" = --recommends ]; then
    recommends=--install-recommends
    shift
  fi
  for pkg in "$@"; do
    installed "$pkg" || missing+=("$pkg")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  log "apt-get install ${missing[*]} ($recommends)"
  retry apt-get "${APT_OPTS[@]}" update -q
  retry apt-get "${APT_OPTS[@]}" install -y -q "$recommends" "${missing[@]}"
}

# The deployment parameter's keys (stacks/twin_host.py writes them; tests/infra keeps the two in step).
# Nothing else is taken from it: whoever can write the parameter must not be able to set PATH, LD_PRELOAD,
# PIP_INDEX_URL or the like for the next root bootstrap.
DEPLOYMENT_KEYS=(DEPLOYMENT_VERSION AGENT_URL SCRIPTS_URL DCV_SECRET_ARN AWS_REGION URL_SUFFIX TOPIC_PREFIX
  DEVICES ARM_RATE_HZ MAX_CONNECTIONS UNITS ROS2 CLIENT_ID_PREFIX DESKTOP_USER LOG_GROUP AGENT_NAME HISTORY_URI
  CALIBRATIONS_URI HOST_STATE_URI RECORD_SESSIONS ALERT_TOPIC_ARN ALERT_WARNINGS SILENT_ALARM)

# load_env FILE [KEY...]: KEY=value lines into exported variables, without executing the file as shell code.
# Only the listed keys are taken (default: DEPLOYMENT_KEYS); any other line is logged and ignored.
load_env() {
  local file="$1" key value allowed
  shift
  local keys=("$@")
  [ ${#keys[@]} -gt 0 ] || keys=("${DEPLOYMENT_KEYS[@]}")
  allowed=" ${keys[*]} "
  while IFS='=' read -r key value || [ -n "$key" ]; do
    case "$key" in '' | \#*) continue ;; esac
    if [[ $allowed != *" $key "* ]]; then
      log "ignoring ${key:0:40} in $file: not a setting this host takes"
      continue
    fi
    printf -v "$key" '%s' "$value"
    export "${key?}"
  done <"$file"
}

# --- signatures ------------------------------------------------------------------------------------------
# The key is fetched with the download it signs, so it proves nothing by itself: its fingerprint is pinned
# (userdata/releases.env) and checked before anything is verified with it.

# Every gpg call here runs with --no-autostart: checking a signature needs only the public key, never
# gpg-agent, and an agent keeps its sockets in the keyring's directory, whose path must fit a Unix socket's
# 108 bytes: under a long TMPDIR (a test runner's, say) the agent could not start. gpg still tries to reach
# one at the end of an import and exits 2 when the path is too long for that, with the key imported; so
# what decides is the keyring's listing (the pinned fingerprint), not the import's exit code.

# gpg_home KEYFILE FINGERPRINT: a throw-away keyring holding KEYFILE, whose primary key must have
# FINGERPRINT; prints the keyring's directory.
gpg_home() {
  local home listing fpr="" line said
  home="$(mktemp -d)"
  said="$(gpg --no-autostart --homedir "$home" --batch --quiet --import "$1" 2>&1 >/dev/null)" || true
  listing="$(gpg --no-autostart --homedir "$home" --batch --with-colons --fingerprint 2>/dev/null)" || true
  # The first fpr line after pub is the primary key's.
  while IFS= read -r line; do
    if [[ $line == fpr:* ]]; then
      fpr="$(cut -d: -f10 <<<"$line")"
      break
    fi
  done <<<"$listing"
  if [ -z "$fpr" ]; then
    echo "gpg could not import $1: ${said//$'\n'/; }" >&2
    rm -rf "$home"
    return 1
  fi
  if [ "$fpr" != "$2" ]; then
    echo "the key in $1 has fingerprint $fpr, not the pinned $2" >&2
    rm -rf "$home"
    return 1
  fi
  echo "$home"
}

# signed_by HOME FINGERPRINT ARGS...: gpg --verify|--decrypt ARGS with the keyring; succeeds only on a valid
# signature whose primary key is FINGERPRINT (VALIDSIG's last field; a key that has expired since signing
# still verifies what it signed).
signed_by() {
  local home="$1" fpr="$2" status line
  shift 2
  status="$(gpg --no-autostart --homedir "$home" --batch --status-fd 1 "$@" 2>/dev/null)" || true
  while IFS= read -r line; do
    if [[ $line == "[GNUPG:] VALIDSIG "* && $line == *" $fpr" ]]; then return 0; fi
  done <<<"$status"
  return 1
}

# verify_detached KEYFILE FINGERPRINT SIGFILE FILE: FILE carries a detached signature by the pinned key.
verify_detached() {
  local home ok=0
  home="$(gpg_home "$1" "$2")" || return 1
  signed_by "$home" "$2" --verify "$3" "$4" || ok=1
  rm -rf "$home"
  if [ "$ok" = 1 ]; then
    echo "$4: no valid signature by $2 in $3" >&2
    return 1
  fi
}

# verify_deb KEYFILE FINGERPRINT DEB: the package's embedded builder signature (the `_gpgbuilder` member
# dpkg-sig writes: a clear-signed list of every other member's md5, sha1 and size) is valid, by the pinned
# key, and matches every member. dpkg-sig itself is gone from Ubuntu 24.04, so the check is spelled out.
verify_deb() {
  local key="$1" fpr="$2" deb="$3" home work members member expected actual problem=""
  home="$(gpg_home "$key" "$fpr")" || return 1
  work="$(mktemp -d)"
  members="$(ar t "$deb")" || problem="$deb is not an ar archive"
  if [ -z "$problem" ] && [[ $'\n'$members$'\n' != *$'\n_gpgbuilder\n'* ]]; then
    problem="$deb carries no builder signature (_gpgbuilder)"
  fi
  if [ -z "$problem" ]; then
    ar p "$deb" _gpgbuilder >"$work/sig.asc"
    rm -f "$work/signed.txt"
    signed_by "$home" "$fpr" --output "$work/signed.txt" --decrypt "$work/sig.asc" ||
      problem="$deb: its builder signature is not a valid signature by $fpr"
  fi
  if [ -z "$problem" ]; then
    while IFS= read -r member; do
      [[ $member == _gpg* ]] && continue
      ar p "$deb" "$member" >"$work/member"
      actual="$(md5sum <"$work/member") $(sha1sum <"$work/member") $(stat -c %s "$work/member")"
      actual="${actual//  -/}"
      expected="$(sed -n "s/^[[:space:]]\{1,\}\([0-9a-f]\{32\} [0-9a-f]\{40\} [0-9]\{1,\}\) ${member//./\\.}\$/\1/p" \
        "$work/signed.txt")"
      if [ "$expected" != "$actual" ]; then
        problem="$deb: member $member does not match its signed checksums (signed: ${expected:-nothing})"
        break
      fi
    done <<<"$members"
  fi
  rm -rf "$home" "$work"
  if [ -n "$problem" ]; then
    echo "$problem" >&2
    return 1
  fi
}

# --- the dpkg lock --------------------------------------------------------------------------------------

# dpkg_lock_holder: prints "PID (command) on PATH" for the first of apt's and dpkg's locks that a process
# holds, nothing when all are free. Asks the kernel (fcntl F_GETLK, the kind of lock apt and dpkg take)
# instead of guessing from process names.
dpkg_lock_holder() {
  python3 - "$ROOT" <<'PY'
import fcntl, os, struct, sys

root = sys.argv[1]
for path in ("/var/lib/dpkg/lock-frontend", "/var/lib/dpkg/lock", "/var/lib/apt/lists/lock",
             "/var/cache/apt/archives/lock"):
    try:
        fd = os.open(root + path, os.O_RDONLY)
    except OSError:
        continue
    try:
        # struct flock on 64-bit Linux: type, whence, start, len, pid (+ padding).
        probe = struct.pack("hhqqi4x", fcntl.F_WRLCK, os.SEEK_SET, 0, 0, 0)
        lock_type, _, _, _, pid = struct.unpack("hhqqi4x", fcntl.fcntl(fd, fcntl.F_GETLK, probe))
    finally:
        os.close(fd)
    if lock_type != fcntl.F_UNLCK:
        try:
            with open(f"/proc/{pid}/comm") as comm:
                name = comm.read().strip()
        except OSError:
            name = "?"
        print(f"{pid} ({name}) on {path}")
        break
PY
}

dpkg_lock_free() {
  LOCK_HOLDER="$(dpkg_lock_holder)"
  [ -z "$LOCK_HOLDER" ]
}

# --- automatic updates held still for a run -------------------------------------------------------------
# unattended-upgrades and the apt timers take the dpkg lock at random times, and a first boot is when they
# have most to do. A run stops and masks them (masked until the next reboot only: --runtime), and restores
# the timers it found active when it ends, whatever the outcome. The record of what to restore survives a
# run that was killed, so the next run (or the next start's checks) restores it.
APT_TIMERS=(apt-daily.timer apt-daily-upgrade.timer)
APT_UNITS=("${APT_TIMERS[@]}" apt-daily.service apt-daily-upgrade.service unattended-upgrades.service)

# hold_apt STATE_DIR
hold_apt() {
  local record="$1/apt-held" unit active=()
  if [ ! -f "$record" ]; then
    for unit in "${APT_TIMERS[@]}" unattended-upgrades.service; do
      if systemctl is-active --quiet "$unit"; then active+=("$unit"); fi
    done
    printf '%s\n' "${active[@]+"${active[@]}"}" >"$record"
  fi
  log "holding apt still: stopping and masking until reboot ${APT_UNITS[*]}"
  # Stopping apt-daily-upgrade lets a running unattended-upgrade finish its current package first.
  timeout 300 systemctl stop "${APT_UNITS[@]}" || log "some apt units did not stop cleanly (see the lock check)"
  systemctl mask --runtime "${APT_UNITS[@]}" >/dev/null
}

# restore_apt STATE_DIR: undo hold_apt (nothing to do without its record).
restore_apt() {
  local record="$1/apt-held" unit active=()
  [ -f "$record" ] || return 0
  while IFS= read -r unit; do
    [ -n "$unit" ] && active+=("$unit")
  done <"$record"
  systemctl unmask --runtime "${APT_UNITS[@]}" >/dev/null
  if [ ${#active[@]} -gt 0 ]; then systemctl start "${active[@]}"; fi
  rm -f "$record"
  log "apt restored: unmasked ${APT_UNITS[*]}; started again: ${active[*]:-none}"
}

# arm_silent_alarm: turn on the actions of the stack's AgentSilent alarm (SILENT_ALARM; stacks/monitoring.py).
# The template creates it with its actions off, because a first boot installs for longer than the alarm's
# 5 minutes before the agent runs; the first boot's end, every update and every start turn them on (the
# call is idempotent, and a deploy that changed the alarm may have turned them off again). Returns 1, with
# FAIL_DETAIL saying why and what to do, when the call fails; nothing to do without SILENT_ALARM.
arm_silent_alarm() {
  local out
  [ -n "${SILENT_ALARM:-}" ] || return 0
  if out="$(aws cloudwatch enable-alarm-actions --region "$AWS_REGION" --alarm-names "$SILENT_ALARM" \
    "${AWS_LIMITS[@]}" 2>&1)"; then
    log "alarm $SILENT_ALARM armed: a silent agent pages from now on"
    return 0
  fi
  FAIL_DETAIL="could not turn on the actions of alarm $SILENT_ALARM (${out:0:300}): a silent agent would page no one; the host role needs cloudwatch:EnableAlarmActions on it (stacks/monitoring.py)"
  log "$FAIL_DETAIL"
  return 1
}
