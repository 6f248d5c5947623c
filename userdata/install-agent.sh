#!/usr/bin/env bash
# Install the so101-twin agent: a Python venv with the agent distribution (package `twin` plus the robot
# model `twin_robots`), its config, its systemd unit (its own unprivileged user, sandboxed), the DCV
# desktop's viewer (autostarted, supervised, running as the desktop user) and the desktop's launcher of the
# operator console (in the desktop user's applications and on the desktop).
#
# Nothing unhashed is ever fetched: the dependencies come from the locked requirements shipped with the
# agent (requirements/host.txt: every package pinned with --hash=sha256, the runtime, the extras a host may
# turn on and the build backend), installed with --require-hashes; the agent itself is then built from the
# shipped source with --no-index and --no-build-isolation (the backend from the lock). Both on the first
# boot and on every update.
#
# Runs as a step of bootstrap.sh on the host, and in tests against a temporary tree with stand-ins for the
# system tools (systemctl, chown, id) first on PATH; the lines are the same in both places:
#   ROOT        install prefix (empty on the host); every path below is written ${ROOT}/...
#   AGENT_SRC   the unpacked agent asset: pyproject.toml, README.md, agents/, robots/, requirements/host.txt
#               (required)
#   PYTHON      interpreter for the venv (default python3.12; mujoco 4 and usd-core 26 need >= 3.11)
#   VENV_ARGS   extra `python -m venv` arguments; PIP_ARGS extra `pip install` arguments
#   AWS_REGION, TOPIC_PREFIX, DEVICES (comma list or *), UNITS, CLIENT_ID_PREFIX, DESKTOP_USER,
#   ARM_RATE_HZ  the arms' publish rate the agent plans its connections for (default 10.0)
#   MAX_CONNECTIONS  the whole fleet's connection bound, as many client ids as the role allows (default 8)
#   RECORD_SESSIONS (true: keep USD recordings in /var/lib/so101-twin-agent/sessions; default false): the settings
#   AGENT_NAME  the CloudWatch metrics' Agent dimension (the stack name; the stack's alarms watch it)
#   HISTORY_URI  where the agent keeps telemetry history (s3://<bucket>/history); empty = no history
#   CALIBRATIONS_URI  where each arm's LeRobot calibration is kept (s3://<bucket>/calibration); empty = none
#   ALERT_TOPIC_ARN  the SNS topic servo alarm transitions are published to; empty = none
#   ALERT_WARNINGS   true: warnings too, not only critical alarms (default false)
#   HOST_STATE_URI  where the host keeps a copy of what lives only on its disk (s3://<bucket>/host): the
#               operator's agent.local.toml, saved whenever it changes and put back by a new host's first
#               boot; the servo alarm state, saved under this host's id whenever the agent writes it, and the
#               newest other host's adopted at a new disk's first install; empty = not kept
#   ROS2         true: publish the arms as ROS 2 JointState (default false; the lock holds the ros2 extra)
# Idempotent: each file is written only when its content differs, pip runs only when the source or the lock
# changed.
set -Eeuo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG_TAG=install-agent
# shellcheck source=userdata/lib.sh
. "$HERE/lib.sh"
PYTHON="${PYTHON:-python3.12}"
VENV_ARGS="${VENV_ARGS:-}"
PIP_ARGS="${PIP_ARGS:-}"
: "${AGENT_SRC:?set AGENT_SRC to the unpacked agent asset (pyproject.toml, agents/, robots/)}"
AWS_REGION="${AWS_REGION:-}"
TOPIC_PREFIX="${TOPIC_PREFIX:-dt/lerobot}"
DEVICES="${DEVICES:-arm-001}"
UNITS="${UNITS:-auto}"
ARM_RATE_HZ="${ARM_RATE_HZ:-10.0}"
MAX_CONNECTIONS="${MAX_CONNECTIONS:-8}"
ROS2="${ROS2:-false}"
CLIENT_ID_PREFIX="${CLIENT_ID_PREFIX:-so101-twin-}"
DESKTOP_USER="${DESKTOP_USER:-ubuntu}"
RECORD_SESSIONS="${RECORD_SESSIONS:-false}"
AGENT_NAME="${AGENT_NAME:-so101-twin}"
HISTORY_URI="${HISTORY_URI:-}"
CALIBRATIONS_URI="${CALIBRATIONS_URI:-}"
HOST_STATE_URI="${HOST_STATE_URI:-}"
ALERT_TOPIC_ARN="${ALERT_TOPIC_ARN:-}"
ALERT_WARNINGS="${ALERT_WARNINGS:-false}"

VENV=/opt/so101-twin/venv
# LOCAL_CONFIG's copy in the stack's bucket (save-local-config.sh), put back by a new host's first boot.
LOCAL_BACKUP="${HOST_STATE_URI:+${HOST_STATE_URI%/}/agent.local.toml}"
LOCAL_SAVER=so101-twin-local-config
# The hosts' copies of the servo alarm state (save-alarm-state.sh), one per host id.
ALARM_BACKUP="${HOST_STATE_URI:+${HOST_STATE_URI%/}/alarm-state/}"
ALARM_SAVER=so101-twin-alarm-state
UNIT=/etc/systemd/system/so101-twin-agent.service
AUTOSTART="/home/${DESKTOP_USER}/.config/autostart/so101-twin-view.desktop"
SUPERVISOR=/opt/so101-twin/bin/twin-view-supervised
# The agent's HTTP address (loopback only) and its operator console there, opened by the desktop's launcher
# in the host's browser (bootstrap.sh installs Firefox, a snap).
HTTP_LISTEN=127.0.0.1:8080
CONSOLE_URL="http://${HTTP_LISTEN}/"
BROWSER=/snap/bin/firefox
LAUNCHER_NAME=so101-twin-console.desktop
LAUNCHER_APPS="/home/${DESKTOP_USER}/.local/share/applications/${LAUNCHER_NAME}"
LAUNCHER_DESKTOP="/home/${DESKTOP_USER}/Desktop/${LAUNCHER_NAME}"
LAUNCHER_TRUST="/home/${DESKTOP_USER}/.config/autostart/so101-twin-console-trust.desktop"
# The agent's own user and the only places it may write (its unit's StateDirectory= and LogsDirectory=).
AGENT_USER=so101-twin
AGENT_STATE=/var/lib/so101-twin-agent
# The agent's shutdown budget and systemd's stop timeout, which must be longer (the margin: the agent's own
# steps after its workers, and the interpreter's exit).
SHUTDOWN_BUDGET_S=60
TIMEOUT_STOP_S=$((SHUTDOWN_BUDGET_S + 30))
SESSIONS="$AGENT_STATE/sessions"
LOCK=requirements/host.txt
PIP=(--disable-pip-version-check --no-input -q --timeout 60 --retries 5)
CHANGED=0

toml_list() {
  local out="" item
  local IFS=,
  # DEVICES='*' means the fleet: split on commas without letting the shell glob it into file names.
  local -
  set -f
  for item in $1; do
    item="${item// /}"
    [ -n "$item" ] && out="${out:+$out, }\"$item\""
  done
  printf '[%s]' "$out"
}

case "$RECORD_SESSIONS" in true) RECORD_DIR="$SESSIONS" ;; false) RECORD_DIR="" ;; *)
  echo "install-agent: RECORD_SESSIONS=$RECORD_SESSIONS is not true or false" >&2
  exit 2
  ;;
esac
case "$UNITS" in ticks | degrees | range100 | auto) ;; *)
  echo "install-agent: UNITS=$UNITS is not one of ticks, degrees, range100, auto" >&2
  exit 2
  ;;
esac
# Both reach the TOML below as numbers (the stack validated them; a number that is not one breaks the file).
[[ $ARM_RATE_HZ =~ ^[0-9]+(\.[0-9]+)?([eE][-+]?[0-9]+)?$ ]] || {
  echo "install-agent: ARM_RATE_HZ=$ARM_RATE_HZ is not a number" >&2
  exit 2
}
[[ $MAX_CONNECTIONS =~ ^[1-9][0-9]*$ ]] || {
  echo "install-agent: MAX_CONNECTIONS=$MAX_CONNECTIONS is not a whole number above 0" >&2
  exit 2
}
case "$ROS2" in true | false) ;; *)
  echo "install-agent: ROS2=$ROS2 is not true or false" >&2
  exit 2
  ;;
esac
case "$ALERT_WARNINGS" in true | false) ;; *)
  echo "install-agent: ALERT_WARNINGS=$ALERT_WARNINGS is not true or false" >&2
  exit 2
  ;;
esac
[ -f "$AGENT_SRC/pyproject.toml" ] || {
  echo "install-agent: $AGENT_SRC has no pyproject.toml; point AGENT_SRC at the unpacked agent asset" >&2
  exit 2
}
[ -f "$AGENT_SRC/$LOCK" ] || {
  echo "install-agent: $AGENT_SRC has no $LOCK, the hashed dependency lock the host installs from; it ships" \
    "with the agent asset (stacks/twin_host.py, AGENT_ASSET_PATTERNS)" >&2
  exit 2
}

# --- the agent's user ------------------------------------------------------------------------------
if ! id -u "$AGENT_USER" >/dev/null 2>&1; then
  useradd --system --user-group --home-dir "$AGENT_STATE" --no-create-home --shell /usr/sbin/nologin "$AGENT_USER"
  log "created system user $AGENT_USER"
fi

# --- venv and the agent package -------------------------------------------------------------------
if [ ! -x "${ROOT}${VENV}/bin/python" ]; then
  log "creating venv ${VENV} with ${PYTHON}"
  # shellcheck disable=SC2086 # VENV_ARGS is a list of flags
  "$PYTHON" -m venv $VENV_ARGS "${ROOT}${VENV}"
  CHANGED=1
fi
# Hash of the shipped source and lock: pip runs again only when either changed (a re-run changes nothing).
src_hash="$(cd "$AGENT_SRC" && find pyproject.toml README.md agents robots "$LOCK" -type f ! -path '*/__pycache__/*' \
  ! -name '*.pyc' -print0 2>/dev/null | LC_ALL=C sort -z | xargs -0 sha256sum | sha256sum)"
src_hash="${src_hash%% *}"
stamp="${ROOT}${VENV}/.so101-twin-source.sha256"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$src_hash" ]; then
  log "installing the locked dependencies ($LOCK, --require-hashes)"
  # shellcheck disable=SC2086 # PIP_ARGS is a list of flags
  "${ROOT}${VENV}/bin/python" -m pip install "${PIP[@]}" --require-hashes --no-deps $PIP_ARGS -r "$AGENT_SRC/$LOCK"
  log "installing the agent package from $AGENT_SRC (no index, no build isolation)"
  build="$(mktemp -d)"
  # Build from a copy: setuptools writes build/ and *.egg-info next to the sources.
  cp -r "$AGENT_SRC"/. "$build"/
  # shellcheck disable=SC2086 # PIP_ARGS is a list of flags
  "${ROOT}${VENV}/bin/python" -m pip install "${PIP[@]}" --no-deps --no-build-isolation --no-index $PIP_ARGS "$build"
  rm -rf "$build"
  printf '%s\n' "$src_hash" >"$stamp"
  CHANGED=1
fi

# --- agent config (the TOML schema `twin run --config` reads) -------------------------------------
write_file "$CONFIG" 0644 <<TOML
# GENERATED by userdata/install-agent.sh from the stack's settings on every deploy: an edit here is lost at
# the next one. Change a setting in twin.settings.toml and deploy, or put your own keys in
# ${LOCAL_CONFIG}, which the agent reads after this file and no deploy touches
# (then: sudo systemctl restart so101-twin-agent).
[broker]
url = "iot"
region = "${AWS_REGION}"
endpoint = ""
client_id_prefix = "${CLIENT_ID_PREFIX}"
ca_file = ""
# The stack's maxConnections: with devices = ["*"] the pool grows to this many connections and the host's
# role allows exactly this many client ids (more, set in the local file, are refused by IoT Core). A device
# list is planned by expected_rate_hz below instead, and the role allows what that plan takes.
max_connections = ${MAX_CONNECTIONS}

[telemetry]
topic_prefix = "${TOPIC_PREFIX}"
devices = $(toml_list "$DEVICES")
units = "${UNITS}"
calibration = ""
# Each arm's own LeRobot calibration, <device>.json (twin calibration push ARM FILE); watched, no restart.
calibrations = "${CALIBRATIONS_URI}"

[twin]
mode = "kinematic"
model = ""
# Recording is off unless the stack sets recordSessions=true: a session file grows for as long as the
# agent runs, and nothing here would bound it.
record_dir = "${RECORD_DIR}"
# Worker processes (docs/scaling.md, "Workers"): 0 = one per vCPU for the whole fleet, fewer for a short
# device list. systemd's stop reaches them through the agent, which lets each flush its history first.
workers = 0
# Acknowledged and latched servo alarms survive a restart or a reboot here (its StateDirectory=).
state_file = "${ALARM_STATE}"
# The Events page over a restart (two files of at most 8 MiB each).
events_file = "${EVENTS_FILE}"
# How long a stop may take (history's last commit); the unit's TimeoutStopSec= is longer.
shutdown_budget_s = ${SHUTDOWN_BUDGET_S}

[health]
# The stack's armRateHz: listed arms are planned on connections for this rate, as the role's client ids are.
expected_rate_hz = ${ARM_RATE_HZ}
stale_periods = 3
offline_after_s = 10.0

[http]
# DEFAULT_HTTP_HOST:DEFAULT_HTTP_PORT of agents/twin/service/config.py; host-check.sh asks this address
# and the console launcher opens it (tests/infra/test_userdata.py keeps them in step).
listen = "${HTTP_LISTEN}"

[history]
uri = "${HISTORY_URI}"
region = "${AWS_REGION}"

[log]
level = "INFO"

[cloudwatch]
# EMF lines the CloudWatch agent ships to the host log group (bootstrap.sh); docs/servo-health.md.
emf_file = "/var/log/so101-twin/emf.log"
agent_name = "${AGENT_NAME}"

[alerts]
# Servo alarm transitions, batched and rate-limited, to the stack's alarm topic (docs/servo-health.md).
topic_arn = "${ALERT_TOPIC_ARN}"
region = "${AWS_REGION}"
warnings = ${ALERT_WARNINGS}

[ros2]
enabled = ${ROS2}
TOML

# --- the operator's file ----------------------------------------------------------------------------
# Written only when it is missing, so a hand edit survives every deploy; a new host (a change that replaced
# the instance) gets the copy the old one saved in the stack's bucket, if there is one.
local_default() {
  cat <<TOML
# Your own agent settings on this host: any key of the agent config (docs/configuration.md), read after
# ${CONFIG}, whose keys it overrides one by one. Deploys never change this file; a copy is kept in the
# stack's bucket whenever it changes, and a host that replaces this one starts with it.
# Apply a change with: sudo systemctl restart so101-twin-agent
#
# [alarms]
# temperature_warning_c = 58.0
TOML
}
local_placeholder() {
  echo "$LOCAL_CONFIG_PLACEHOLDER"
  echo "# (from ${LOCAL_BACKUP}; until then this file holds no settings of yours and is not saved)"
  local_default
}

# restore_local_config: 0 the saved copy is in place, 1 none is saved, 2 it could not be read (logged).
# Listed first: S3 answers a GET of a missing key with 403, not 404, to a role that may not list the bucket,
# and the listing's count tells "none saved" from "not readable" either way. One page of it (--no-paginate,
# up to 1,000 keys): the AWS CLI's docs allow --query with --output text on a paginated response only on
# what it lists (Contents, CommonPrefixes), which KeyCount is not.
restore_local_config() {
  local bucket="${LOCAL_BACKUP#s3://}" key count tmp region=()
  key="${bucket#*/}"
  bucket="${bucket%%/*}"
  [ -z "$AWS_REGION" ] || region=(--region "$AWS_REGION")
  if ! count="$(aws s3api list-objects-v2 "${AWS_LIMITS[@]}" "${region[@]}" --no-paginate \
    --bucket "$bucket" --prefix "$key" --query KeyCount --output text 2>&1)"; then
    log "could not look for the saved ${LOCAL_CONFIG} at ${LOCAL_BACKUP}: ${count}"
    return 2
  fi
  [ "$count" != 0 ] || return 1
  tmp="$(mktemp "$(dirname "${ROOT}${LOCAL_CONFIG}")/.so101-twin.XXXXXX")"
  if ! aws s3 cp "${AWS_LIMITS[@]}" "${region[@]}" --only-show-errors "$LOCAL_BACKUP" "$tmp"; then
    rm -f "$tmp"
    log "could not read the saved ${LOCAL_CONFIG} at ${LOCAL_BACKUP}"
    return 2
  fi
  chmod 0644 "$tmp"
  durable_mv "$tmp" "${ROOT}${LOCAL_CONFIG}"
  CHANGED=1
}

mkdir -p "$(dirname "${ROOT}${LOCAL_CONFIG}")"
# Tried again while the file is the untouched placeholder of a copy that could not be read.
if [ -n "$LOCAL_BACKUP" ] && { [ ! -f "${ROOT}${LOCAL_CONFIG}" ] ||
  cmp -s <(local_placeholder) "${ROOT}${LOCAL_CONFIG}"; }; then
  outcome=0
  restore_local_config || outcome=$?
  case "$outcome" in
    0) log "restored ${LOCAL_CONFIG} from ${LOCAL_BACKUP}" ;;
    1) write_file "$LOCAL_CONFIG" 0644 < <(local_default) ;;
    *)
      [ -f "${ROOT}${LOCAL_CONFIG}" ] || write_file "$LOCAL_CONFIG" 0644 < <(local_placeholder)
      log "warning: ${LOCAL_CONFIG} is a placeholder until the saved copy can be read (the next deploy" \
        "tries again); the agent runs without those settings meanwhile"
      ;;
  esac
fi
[ -f "${ROOT}${LOCAL_CONFIG}" ] || write_file "$LOCAL_CONFIG" 0644 < <(local_default)

# --- the servo alarms of the host this one replaces -----------------------------------------------
# adopt_alarm_state: 0 the newest other host's copy is in place (ADOPTED says which, with its alarms), 1 no
# other host saved one, 2 it could not be read or is not a valid state file (logged).
adopt_alarm_state() {
  local bucket="${ALARM_BACKUP#s3://}" prefix listing own newest tmp out region=()
  prefix="${bucket#*/}"
  bucket="${bucket%%/*}"
  own="${prefix}$(cat "${ROOT}${HOST_ID_FILE}").json"
  [ -z "$AWS_REGION" ] || region=(--region "$AWS_REGION")
  # One page, as above: one key per host, far fewer than its 1,000.
  if ! listing="$(aws s3api list-objects-v2 "${AWS_LIMITS[@]}" "${region[@]}" --no-paginate \
    --bucket "$bucket" --prefix "$prefix" --query 'Contents[].[LastModified,Key]' --output text 2>&1)"; then
    log "could not look for the servo alarm state saved at ${ALARM_BACKUP}: ${listing}"
    return 2
  fi
  # The copy written last (S3's LastModified, ISO 8601 in UTC, sorts as text): the host in service writes
  # its copy at every start and stop of its agent, while one whose first boot failed and was rolled back
  # wrote only then. One line per key, "None" for no key.
  newest="$(printf '%s\n' "$listing" | awk -v own="$own" 'NF == 2 && $2 != own' | sort | tail -n 1 |
    cut -f 2)"
  [ -n "$newest" ] || return 1
  tmp="$(mktemp "${TMPDIR:-/tmp}/so101-twin-alarm-state.XXXXXX")"
  if ! aws s3 cp "${AWS_LIMITS[@]}" "${region[@]}" --only-show-errors "s3://${bucket}/${newest}" "$tmp"; then
    rm -f "$tmp"
    log "could not read the servo alarm state saved at s3://${bucket}/${newest}"
    return 2
  fi
  if ! out="$("${ROOT}${VENV}/bin/python" -c 'import sys
from twin.service.persist import adopt_file
print(adopt_file(sys.argv[1], sys.argv[2]))' "$tmp" "${ROOT}${ALARM_STATE}" 2>&1)"; then
    rm -f "$tmp"
    log "the servo alarm state saved at s3://${bucket}/${newest} is not one the agent can read; not used:" \
      "${out##*$'\n'}"
    return 2
  fi
  rm -f "$tmp"
  chown -R "${AGENT_USER}:" "${ROOT}${AGENT_STATE}"
  ADOPTED="s3://${bucket}/${newest} (${out} alarms)"
}

# A new disk (no host id yet) is a new host: its agent starts with the alarms the host it replaces kept,
# acknowledgements included. Tried once, before its agent first runs; afterwards the agent's own file is
# the host's state.
if [ ! -s "${ROOT}${HOST_ID_FILE}" ]; then
  mkdir -p "$(dirname "${ROOT}${HOST_ID_FILE}")"
  printf '%s-%s\n' "$(date -u +%Y%m%dT%H%M%SZ)" "$(od -An -N4 -tx4 /dev/urandom | tr -d ' ')" \
    >"${ROOT}${HOST_ID_FILE}"
  log "host id $(cat "${ROOT}${HOST_ID_FILE}")"
  if [ -n "$ALARM_BACKUP" ] && [ ! -e "${ROOT}${ALARM_STATE}" ]; then
    mkdir -p "${ROOT}${AGENT_STATE}"
    ADOPTED=""
    outcome=0
    adopt_alarm_state || outcome=$?
    case "$outcome" in
      0) log "servo alarm state adopted from ${ADOPTED}" ;;
      1) log "no other host saved a servo alarm state at ${ALARM_BACKUP}: the agent starts without one" ;;
      *)
        log "warning: the servo alarms of the host this one replaces are not carried over (above); their" \
          "e-mails were sent when they changed, and their copy stays in the bucket under ${ALARM_BACKUP}"
        ;;
    esac
  fi
fi

# --- the agent service ----------------------------------------------------------------------------
# Its own user, no capabilities, a read-only system but for its state and log directories: the agent
# parses untrusted MQTT payloads with native parsers, so what it can reach is kept small.
write_file "$UNIT" 0644 <<UNIT
[Unit]
Description=so101-twin agent: mirrors SO-101 telemetry from IoT Core into MuJoCo and USD
Wants=network-online.target
After=network-online.target

[Service]
# \`twin run\` tells systemd when it is up (READY=1: its mirrors run and HTTP answers), so the host checks
# ordered after this unit find it serving, and pings the watchdog from its main thread every few seconds: one
# that stops (a native call stuck holding the GIL, a deadlock) is killed after WatchdogSec, with every
# thread's stack in the journal, and started again (agents/twin/service/systemd.py).
Type=notify
NotifyAccess=main
WatchdogSec=60
# Its workers may take up to 120 s to start (shards.START_TIMEOUT_S), history's writer too, side by side.
TimeoutStartSec=300
User=${AGENT_USER}
Group=${AGENT_USER}
# MuJoCo renders offscreen through EGL on the GPU (/dev/nvidia*); no X display for the service.
SupplementaryGroups=video
ExecStart=${VENV}/bin/twin run --config ${CONFIG} --config ${LOCAL_CONFIG}
Environment=MUJOCO_GL=egl
Environment=PYTHONUNBUFFERED=1
Environment=HOME=${AGENT_STATE}
Environment=MPLCONFIGDIR=${AGENT_STATE}/matplotlib
Restart=always
RestartSec=5
# \`twin run\` exits 2 on a configuration error (agents/twin/cli/commands/run.py, EXIT_CONFIG) and logs
# the setting: restarting cannot fix it, so systemd leaves it stopped and failed.
RestartPreventExitStatus=2
# The agent's stop takes up to [twin] shutdown_budget_s (its workers flush history, then are killed); systemd
# must not SIGKILL it first.
TimeoutStopSec=${TIMEOUT_STOP_S}
SyslogIdentifier=so101-twin-agent
StateDirectory=so101-twin-agent
StateDirectoryMode=0750
# /var/log/so101-twin: the EMF file for CloudWatch.
LogsDirectory=so101-twin
NoNewPrivileges=yes
ProtectSystem=strict
ReadWritePaths=-${AGENT_STATE} -/var/log/so101-twin
ProtectHome=yes
PrivateTmp=yes
CapabilityBoundingSet=
AmbientCapabilities=
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectControlGroups=yes
RestrictSUIDSGID=yes
RestrictRealtime=yes
RestrictNamespaces=yes
LockPersonality=yes
SystemCallArchitectures=native
RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK
UMask=0027

[Install]
WantedBy=multi-user.target
UNIT

# --- copies in the stack's bucket of what lives only on this disk, whenever it changes ------------------
# saver_units NAME SCRIPT TARGET WATCHED WHAT: a oneshot service that runs the host's own copy of SCRIPT
# TARGET, as root, which alone may read all of /etc and the agent's state here, and a path unit that starts
# it whenever WATCHED changes: an editor's save, the agent's atomic write (a rename), or a restore above.
saver_units() {
  local name="$1" script="$2" target="$3" watched="$4" what="$5"
  write_file "/etc/systemd/system/${name}.service" 0644 <<UNIT
[Unit]
Description=so101-twin: save ${what} (${watched}) to the stack's bucket
Wants=network-online.target
After=network-online.target

[Service]
Type=oneshot
ExecStart=/bin/bash /opt/so101-twin/userdata/${script} ${target}
Environment=AWS_REGION=${AWS_REGION} AGENT_NAME=${AGENT_NAME}
SyslogIdentifier=${name}
UNIT
  write_file "/etc/systemd/system/${name}.path" 0644 <<UNIT
[Unit]
Description=so101-twin: keep a copy of ${what} (${watched}) when it changes

[Path]
PathChanged=${watched}

[Install]
WantedBy=multi-user.target
UNIT
}
if [ -n "$ALARM_BACKUP" ]; then
  saver_units "$ALARM_SAVER" save-alarm-state.sh "$ALARM_BACKUP" "$ALARM_STATE" "the agent's servo alarm state"
fi
if [ -n "$LOCAL_BACKUP" ]; then
  saver_units "$LOCAL_SAVER" save-local-config.sh "$LOCAL_BACKUP" "$LOCAL_CONFIG" "the operator's agent settings"
fi

# --- the viewer in the DCV console session --------------------------------------------------------
# GNOME starts autostart entries once per login and never again; the supervisor restarts the viewer when
# it exits and when a deploy replaces the agent package.
write_file "$SUPERVISOR" 0755 <"$HERE/view-supervisor.sh"
write_file "$AUTOSTART" 0644 <<DESKTOP
[Desktop Entry]
Type=Application
Name=SO-101 twin viewer
Comment=Live MuJoCo view of the arm, following the local so101-twin agent (restarted when it exits)
Exec=${SUPERVISOR}
Terminal=false
X-GNOME-Autostart-enabled=true
X-GNOME-Autostart-Delay=5
DESKTOP

# --- the operator console's launcher ----------------------------------------------------------------
# In GNOME's applications (search "console") and as an icon on the desktop. The desktop's icons (Ubuntu's
# Desktop Icons NG) launch only a desktop file that is executable and marked trusted; the mark is a GIO
# metadata attribute of the user's session, so a one-shot autostart entry sets it at login.
launcher() {
  cat <<DESKTOP
[Desktop Entry]
Type=Application
Name=SO-101 operator console
Comment=The fleet, each arm's alarms and live charts, sessions and events, served by the local so101-twin agent
Exec=${BROWSER} --new-window ${CONSOLE_URL}
Icon=firefox
Terminal=false
Categories=System;Monitor;
DESKTOP
}
write_file "$LAUNCHER_APPS" 0755 < <(launcher)
write_file "$LAUNCHER_DESKTOP" 0755 < <(launcher)
write_file "$LAUNCHER_TRUST" 0644 <<DESKTOP
[Desktop Entry]
Type=Application
Name=SO-101 console launcher: trusted
Comment=Lets the desktop icon of the operator console launch (a GIO metadata mark of the session)
Exec=gio set ${LAUNCHER_DESKTOP} metadata::trusted true
Terminal=false
NoDisplay=true
X-GNOME-Autostart-enabled=true
DESKTOP

if [ -n "$RECORD_DIR" ]; then
  mkdir -p "${ROOT}${SESSIONS}"
  chown "$AGENT_USER:" "${ROOT}${SESSIONS}"
fi

if id -u "$DESKTOP_USER" >/dev/null 2>&1; then
  # Written by root above; the desktop user's GNOME must own its ~/.config to write settings there, and
  # its ~/.local and ~/Desktop, where the launchers are, to keep or move them.
  chown -R "$DESKTOP_USER:" "${ROOT}/home/${DESKTOP_USER}/.config" "${ROOT}/home/${DESKTOP_USER}/.local" \
    "${ROOT}/home/${DESKTOP_USER}/Desktop"
fi
systemctl daemon-reload
systemctl enable so101-twin-agent.service >/dev/null 2>&1
if [ -n "$LOCAL_BACKUP" ]; then
  systemctl enable --now "${LOCAL_SAVER}.path" >/dev/null 2>&1
  # Saved now too: the path unit sees changes from here on, and a host that ran before it existed has a
  # file nobody saved yet. A failure only delays the copy to the file's next change or the next deploy.
  AGENT_NAME="$AGENT_NAME" bash "$HERE/save-local-config.sh" "$LOCAL_BACKUP" ||
    log "warning: ${LOCAL_CONFIG} could not be saved to ${LOCAL_BACKUP} now; it is saved at its next change"
fi
if [ -n "$ALARM_BACKUP" ]; then
  systemctl enable --now "${ALARM_SAVER}.path" >/dev/null 2>&1
  # Saved now too, for a host whose agent wrote its file before the path unit existed (an update).
  AGENT_NAME="$AGENT_NAME" SAVE_EVERY_S=0 bash "$HERE/save-alarm-state.sh" "$ALARM_BACKUP" ||
    log "warning: ${ALARM_STATE} could not be saved to ${ALARM_BACKUP} now; it is saved at its next change"
fi
if [ "$CHANGED" = 1 ] || ! systemctl is-active --quiet so101-twin-agent.service; then
  # Not waited for (a notify unit's restart waits for READY=1): the host check after the install says
  # whether it came up, naming the setting when it refused its configuration.
  systemctl restart --no-block so101-twin-agent.service
  log "agent service (re)start requested"
fi
log "done (changed=$CHANGED)"
