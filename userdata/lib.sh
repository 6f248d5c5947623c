# shellcheck shell=bash
# Helpers shared by bootstrap.sh and install-agent.sh (sourced, never run).
#
# ROOT is the install prefix: empty on the host, a temporary directory in the tests. Every path a script
# touches is written "${ROOT}/..."; every system tool is called by name through PATH, so the tests put
# stand-ins first on PATH and the very same lines run in both places.

ROOT="${ROOT:-}"
ROOT="${ROOT%/}"
CHANGED="${CHANGED:-0}"

log() { echo "${LOG_TAG:-so101-twin}: $(date -Is) $*"; }

# retry CMD...: five tries, 10/20/30/40 s apart (apt mirrors and CDNs have bad minutes, not bad hours).
retry() {
  local n
  for n in 1 2 3 4 5; do
    if "$@"; then return 0; fi
    [ "$n" = 5 ] && break
    log "retry $n/4 in $((n * 10)) s: $*"
    sleep $((n * 10))
  done
  log "gave up after 5 tries: $*"
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

# apt waits for the dpkg lock instead of failing: on a first boot, unattended-upgrades often holds it.
APT_OPTS=(-o DPkg::Lock::Timeout=600)

apt_install() {
  local missing=() pkg
  for pkg in "$@"; do
    installed "$pkg" || missing+=("$pkg")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  log "apt-get install ${missing[*]}"
  retry apt-get "${APT_OPTS[@]}" update -q
  retry apt-get "${APT_OPTS[@]}" install -y -q --no-install-recommends "${missing[@]}"
}

# load_env FILE: KEY=value lines (the stack's deployment settings) into variables, without executing the
# file as shell code; only upper-case keys are taken.
load_env() {
  local key value
  while IFS='=' read -r key value || [ -n "$key" ]; do
    case "$key" in
      '' | \#*) continue ;;
      *[!A-Z0-9_]*)
        log "ignoring malformed line in $1: $key"
        continue
        ;;
    esac
    printf -v "$key" '%s' "$value"
    export "${key?}"
  done <"$1"
}
