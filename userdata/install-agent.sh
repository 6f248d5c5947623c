#!/usr/bin/env bash
# Install the so101-twin agent: a Python venv with the agent distribution (package `twin` plus the robot
# model `twin_robots`), its config, its systemd unit (its own unprivileged user, sandboxed) and the DCV
# desktop's viewer (autostarted, supervised, running as the desktop user).
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
#   RECORD_SESSIONS (true: keep USD recordings in /var/lib/so101-twin-agent/sessions; default false): the settings
#   AGENT_NAME  the CloudWatch metrics' Agent dimension (the stack name; the stack's alarms watch it)
#   HISTORY_URI  where the agent keeps telemetry history (s3://<bucket>/history); empty = no history
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
ROS2="${ROS2:-false}"
CLIENT_ID_PREFIX="${CLIENT_ID_PREFIX:-so101-twin-}"
DESKTOP_USER="${DESKTOP_USER:-ubuntu}"
RECORD_SESSIONS="${RECORD_SESSIONS:-false}"
AGENT_NAME="${AGENT_NAME:-so101-twin}"
HISTORY_URI="${HISTORY_URI:-}"

VENV=/opt/so101-twin/venv
CONFIG=/etc/so101-twin/agent.toml
UNIT=/etc/systemd/system/so101-twin-agent.service
AUTOSTART="/home/${DESKTOP_USER}/.config/autostart/so101-twin-view.desktop"
SUPERVISOR=/opt/so101-twin/bin/twin-view-supervised
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
case "$ROS2" in true | false) ;; *)
  echo "install-agent: ROS2=$ROS2 is not true or false" >&2
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
# Rendered by userdata/install-agent.sh from the stack settings; re-deploy to change it.
[broker]
url = "iot"
region = "${AWS_REGION}"
endpoint = ""
client_id_prefix = "${CLIENT_ID_PREFIX}"
ca_file = ""

[telemetry]
topic_prefix = "${TOPIC_PREFIX}"
devices = $(toml_list "$DEVICES")
units = "${UNITS}"
calibration = ""

[twin]
mode = "kinematic"
model = ""
# Recording is off unless the stack sets recordSessions=true: a session file grows for as long as the
# agent runs, and nothing here would bound it.
record_dir = "${RECORD_DIR}"
# Worker processes (docs/agent.md, "Workers"): 0 = one per vCPU for the whole fleet, fewer for a short
# device list. systemd's stop reaches them through the agent, which lets each flush its history first.
workers = 0
# Acknowledged and latched servo alarms survive a restart or a reboot here (its StateDirectory=).
state_file = "${AGENT_STATE}/state.json"
# How long a stop may take (history's last commit); the unit's TimeoutStopSec= is longer.
shutdown_budget_s = ${SHUTDOWN_BUDGET_S}

[health]
expected_rate_hz = 10.0
stale_periods = 3
offline_after_s = 10.0

[http]
# DEFAULT_HTTP_HOST:DEFAULT_HTTP_PORT of agents/twin/service/config.py; host-check.sh asks this address
# (tests/infra/test_userdata.py keeps the three in step).
listen = "127.0.0.1:8080"

[history]
uri = "${HISTORY_URI}"
region = "${AWS_REGION}"

[log]
level = "INFO"

[cloudwatch]
# EMF lines the CloudWatch agent ships to the host log group (bootstrap.sh); docs/servo-health.md.
emf_file = "/var/log/so101-twin/emf.log"
agent_name = "${AGENT_NAME}"

[ros2]
enabled = ${ROS2}
TOML

# --- the agent service ----------------------------------------------------------------------------
# Its own user, no capabilities, a read-only system but for its state and log directories: the agent
# parses untrusted MQTT payloads with native parsers, so what it can reach is kept small.
write_file "$UNIT" 0644 <<UNIT
[Unit]
Description=so101-twin agent: mirrors SO-101 telemetry from IoT Core into MuJoCo and USD
Wants=network-online.target
After=network-online.target

[Service]
Type=simple
User=${AGENT_USER}
Group=${AGENT_USER}
# MuJoCo renders offscreen through EGL on the GPU (/dev/nvidia*); no X display for the service.
SupplementaryGroups=video
ExecStart=${VENV}/bin/twin run --config ${CONFIG}
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

if [ -n "$RECORD_DIR" ]; then
  mkdir -p "${ROOT}${SESSIONS}"
  chown "$AGENT_USER:" "${ROOT}${SESSIONS}"
fi

if id -u "$DESKTOP_USER" >/dev/null 2>&1; then
  # Written by root above; the desktop user's GNOME must own its ~/.config to write settings there.
  chown -R "$DESKTOP_USER:" "${ROOT}/home/${DESKTOP_USER}/.config"
fi
systemctl daemon-reload
systemctl enable so101-twin-agent.service >/dev/null 2>&1
if [ "$CHANGED" = 1 ] || ! systemctl is-active --quiet so101-twin-agent.service; then
  systemctl restart so101-twin-agent.service
  log "agent service (re)started"
fi
log "done (changed=$CHANGED)"
