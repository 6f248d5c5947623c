#!/usr/bin/env bash
# Sets up the so101-twin host and proves it works; started by the UserData (user-data.sh) with the
# deployment settings it read from the stack's SSM parameter:
#   bash bootstrap.sh /etc/so101-twin/deployment.env
# Steps, in order (docs/deploy.md has the timeline and why each differs from AWS's DCV recipe):
#   logs      CloudWatch agent shipping this log (from its first line), the agent's and DCV's
#   packages  GNOME (ubuntu-desktop-minimal), GDM, mesa-utils, dpkg-dev, python3.12-venv
#   gpu       the NVIDIA GPU, and the Xorg module matching its driver
#   agent     install-agent.sh: venv, config, service, supervised viewer autostart
#   desktop   GDM (Xorg, auto-login), GNOME without first-run wizard/blanking/lock, ~/.config owned by the
#             user, xorg.conf for a monitor-less GPU (virtual screen, AllowEmptyInitialConfiguration)
#   password  the desktop user's password (the DCV login) from Secrets Manager
#   dcv       Amazon DCV server + web viewer, automatic console session owned by the desktop user
#   display   X (GDM) first, then DCV, then the console session
#   verify    host-check.sh: X on the GPU, the DCV console session, the agent subscribed, the viewer
# First boot (SO101_TWIN_MODE=boot) ends by signalling CloudFormation: SUCCESS after verify, FAILURE from
# the first failing step with its name and the last log lines. An update (SO101_TWIN_MODE=update, the SSM
# association) runs the same steps, which only change what differs, and reports through its exit status.
set -Eeuo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG_TAG=bootstrap
# shellcheck source=userdata/lib.sh
. "$HERE/lib.sh"
# shellcheck source=userdata/host-check.sh
. "$HERE/host-check.sh"

DEPLOYMENT="${1:-$ROOT/etc/so101-twin/deployment.env}"
MODE="${SO101_TWIN_MODE:-boot}"
LOG="$ROOT/var/log/so101-twin-bootstrap.log"
STATE="$ROOT/var/lib/so101-twin"
VENV=/opt/so101-twin/venv
XORG_CONF=/etc/X11/xorg.conf
DCV_CDN="${DCV_CDN:-https://d1uj6qtbmh3dt5.cloudfront.net}"
# The largest screen a DCV web client may ask for (dcv.conf) and the X screen's virtual size: with no
# monitor attached the NVIDIA driver has no mode to start from, so X needs the size given.
VIRTUAL_SCREEN=4096x2160
# Polls for the things that start asynchronously (tries x 5 s): X, the DCV session, the agent, the viewer.
WAIT_X_TRIES=60
WAIT_DCV_TRIES=36
WAIT_AGENT_TRIES=60
WAIT_VIEWER_TRIES=36

if [ -z "${SO101_TWIN_LOGGING:-}" ]; then
  mkdir -p "$(dirname "$LOG")"
  exec > >(tee -a "$LOG") 2>&1
  export SO101_TWIN_LOGGING=1
fi
mkdir -p "$STATE"

export DEBIAN_FRONTEND=noninteractive
STEP=settings
FAIL_DETAIL=""
GPU=0
DISPLAY_CHANGED=0

# die MESSAGE: fail the current step with a message that says what is wrong.
die() {
  FAIL_DETAIL="$*"
  log "$*"
  return 1
}

# signal STATUS REASON: tell CloudFormation how the first boot ended. The wait condition (a pre-signed
# URL) carries the reason into the `cdk deploy` output; SignalResource answers the instance's
# CreationPolicy but has no field for a reason.
signal() {
  local status="$1" reason="$2" instance body
  instance="$(cat "$ROOT/var/lib/cloud/data/instance-id" 2>/dev/null || echo unknown)"
  if [ -z "${SO101_TWIN_STACK:-}" ]; then
    log "no stack to signal (SO101_TWIN_STACK unset): $status"
    return 0
  fi
  body="$(python3 -c 'import json, sys; print(json.dumps({"Status": sys.argv[1], "Reason": sys.argv[2][-3000:], "UniqueId": sys.argv[3], "Data": sys.argv[2][:200]}))' "$status" "$reason" "$instance")"
  if [ -n "${SO101_TWIN_HANDLE:-}" ]; then
    curl -fsS -X PUT -H 'Content-Type:' --data-binary "$body" "$SO101_TWIN_HANDLE" ||
      log "could not post to the wait condition (it may be complete already)"
  fi
  aws cloudformation signal-resource --region "${AWS_REGION:-${SO101_TWIN_REGION:-}}" \
    --stack-name "$SO101_TWIN_STACK" --logical-resource-id "${SO101_TWIN_RESOURCE:-}" \
    --unique-id "$instance" --status "$status" ||
    log "signal-resource $status failed"
  log "signalled $status to $SO101_TWIN_STACK/${SO101_TWIN_RESOURCE:-}"
}

# finish STATUS SUMMARY: record the outcome on the host; on the first boot, signal it.
finish() {
  local status="$1" summary="$2" tail_text
  printf '%s %s %s %s\n' "$(date -Is)" "$MODE" "$status" "$summary" >"$STATE/last-run"
  if [ "$status" = SUCCESS ] && [ "$(cat "$STATE/deployed-version" 2>/dev/null)" != "${DEPLOYMENT_VERSION:-}" ]; then
    printf '%s\n' "$DEPLOYMENT_VERSION" >"$STATE/deployed-version"
  fi
  [ "$MODE" = boot ] || return 0
  sleep 1 # let tee write the last lines before they are quoted
  tail_text="$(tail -n 12 "$LOG" 2>/dev/null || true)"
  [ "${#tail_text}" -le 1500 ] || tail_text="...${tail_text: -1500}"
  signal "$status" "$summary; last log lines: $tail_text"
}

on_error() {
  local rc=$?
  trap - ERR
  # In a subshell ($(...), a pipeline) only leave it; the parent sees the failure and reports it once.
  [ "$BASHPID" = "$$" ] || exit "$rc"
  log "step $STEP FAILED (exit $rc, line ${BASH_LINENO[0]}) ${FAIL_DETAIL}"
  finish FAILURE "step $STEP failed (exit $rc)${FAIL_DETAIL:+: $FAIL_DETAIL}"
  exit "$rc"
}
trap on_error ERR

load_env "$DEPLOYMENT"
for setting in AWS_REGION DCV_SECRET_ARN DESKTOP_USER DEPLOYMENT_VERSION LOG_GROUP TOPIC_PREFIX DEVICES UNITS \
  CLIENT_ID_PREFIX; do
  [ -n "${!setting:-}" ] || die "$DEPLOYMENT has no $setting: the stack's deployment parameter is incomplete"
done
URL_SUFFIX="${URL_SUFFIX:-amazonaws.com}"

run_step() {
  local t0=$SECONDS
  STEP="$1"
  shift
  log "step $STEP: start"
  "$@"
  log "step $STEP: done in $((SECONDS - t0)) s"
}

# --- logs: to CloudWatch from the first step ------------------------------------------------------
step_logs() {
  local ctl="$ROOT/opt/aws/amazon-cloudwatch-agent/bin/amazon-cloudwatch-agent-ctl" deb arch
  if [ ! -x "$ctl" ]; then
    arch="$(dpkg --print-architecture)"
    deb="$(mktemp --suffix=.deb)"
    # The regional bucket, partition-aware through the URL suffix (amazonaws.com, amazonaws.com.cn).
    retry curl -fsSL -o "$deb" \
      "https://amazoncloudwatch-agent-${AWS_REGION}.s3.${AWS_REGION}.${URL_SUFFIX}/ubuntu/${arch}/latest/amazon-cloudwatch-agent.deb"
    retry apt-get "${APT_OPTS[@]}" install -y -q "$deb"
    rm -f "$deb"
    [ -x "$ctl" ] || die "the CloudWatch agent package did not install $ctl"
  fi
  CHANGED=0
  # rsyslog copies the agent's journal lines to a file the CloudWatch agent can follow.
  write_file /etc/rsyslog.d/30-so101-twin.conf 0644 <<'RSYSLOG'
# Managed by so101-twin bootstrap.sh: the agent's log as a file for the CloudWatch agent.
:programname, isequal, "so101-twin-agent" /var/log/so101-twin-agent.log
RSYSLOG
  # rsyslog ships with Ubuntu server images; the packages step installs it otherwise and it reads the rule then.
  if [ "$CHANGED" = 1 ] && installed rsyslog; then systemctl restart rsyslog; fi
  write_file /etc/logrotate.d/so101-twin 0644 <<'ROTATE'
# Managed by so101-twin bootstrap.sh: bound the host's own logs on disk (CloudWatch keeps them a year).
/var/log/so101-twin-bootstrap.log /var/log/so101-twin-agent.log {
  weekly
  rotate 4
  maxsize 50M
  compress
  missingok
  notifempty
  copytruncate
}
ROTATE
  CHANGED=0
  # The agent's Embedded Metric Format lines: CloudWatch Logs turns each into the SO101Twin metrics the
  # stack's alarms watch (agents/twin/output/emf.py, stacks/monitoring.py).
  local EMF_FILE=/var/log/so101-twin/emf.log
  # The agent reads new files from their beginning (its JSON config defaults to from_beginning), so the
  # lines the UserData wrote before this step reach CloudWatch too.
  write_file /opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json 0644 <<JSON
{"logs": {"logs_collected": {"files": {"collect_list": [
  {"file_path": "/var/log/so101-twin-bootstrap.log", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/bootstrap"},
  {"file_path": "/var/log/so101-twin-agent.log", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/agent"},
  {"file_path": "/var/log/dcv/server.log", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/dcv"},
  {"file_path": "${EMF_FILE}", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/emf"}]}}}}
JSON
  if [ "$CHANGED" = 1 ] || ! systemctl is-active --quiet amazon-cloudwatch-agent; then
    "$ctl" -a fetch-config -m ec2 -s -c "file:/opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json"
  fi
}

# --- packages -------------------------------------------------------------------------------------
step_packages() {
  # dpkg-dev: the DCV server's postinst calls dpkg-architecture. python3.12-venv: the agent's venv.
  apt_install ubuntu-desktop-minimal gdm3 mesa-utils dpkg-dev python3.12-venv curl rsyslog
}

# --- the GPU and the Xorg driver module matching it -----------------------------------------------
nvidia_xorg_module() {
  [ -e "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] ||
    [ -e "$ROOT/usr/lib/aarch64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] ||
    [ -e "$ROOT/usr/lib/xorg/modules/drivers/nvidia_drv.so" ]
}

# The packaged driver's flavour, e.g. 580-server from libnvidia-gl-580-server; the Xorg module package
# must be the same flavour or X and the kernel module disagree.
nvidia_flavour() {
  local listing pkg status version
  listing="$(dpkg-query -W -f='${Package} ${Status}\n' 'libnvidia-gl-*' 2>/dev/null || true)"
  while read -r pkg status; do
    if [ "$status" = "install ok installed" ]; then
      echo "${pkg#libnvidia-gl-}"
      return 0
    fi
  done <<<"$listing"
  version="$(nvidia-smi --query-gpu=driver_version --format=csv,noheader)"
  version="${version%%$'\n'*}"
  echo "${version%%.*}-server"
}

step_gpu() {
  local gpus flavour
  if ! command -v nvidia-smi >/dev/null 2>&1; then
    log "no nvidia-smi: no NVIDIA driver; the console session gets a dummy X screen (no GPU rendering)"
    GPU=0
    apt_install xserver-xorg-video-dummy
    return 0
  fi
  gpus="$(nvidia-smi -L)" || die "nvidia-smi -L failed: the NVIDIA driver is not working"
  [[ $gpus == *GPU* ]] || die "nvidia-smi lists no GPU: $gpus"
  GPU=1
  log "GPU: ${gpus//$'\n'/; }"
  if ! nvidia_xorg_module; then
    flavour="$(nvidia_flavour)"
    log "the NVIDIA Xorg module is missing; installing xserver-xorg-video-nvidia-$flavour"
    apt_install "xserver-xorg-video-nvidia-$flavour"
    nvidia_xorg_module || die "xserver-xorg-video-nvidia-$flavour installed no nvidia_drv.so"
  fi
}

# --- the agent ------------------------------------------------------------------------------------
step_agent() {
  AGENT_SRC="$ROOT/opt/so101-twin/agent-src" PYTHON="${PYTHON:-python3.12}" AWS_REGION="$AWS_REGION" \
    TOPIC_PREFIX="$TOPIC_PREFIX" DEVICES="$DEVICES" UNITS="$UNITS" CLIENT_ID_PREFIX="$CLIENT_ID_PREFIX" \
    DESKTOP_USER="$DESKTOP_USER" RECORD_SESSIONS="${RECORD_SESSIONS:-false}" \
    AGENT_NAME="${AGENT_NAME:-so101-twin}" HISTORY_URI="${HISTORY_URI:-}" ROS2="${ROS2:-false}" \
    bash "$HERE/install-agent.sh"
}

# --- desktop: GDM on Xorg with auto-login, a quiet GNOME, X for a monitor-less GPU ----------------
xorg_conf_ok() {
  local text
  text="$(cat "${ROOT}${XORG_CONF}" 2>/dev/null)" || return 1
  [[ $text == *'Driver'*'"nvidia"'* && $text == *AllowEmptyInitialConfiguration* && $text == *Virtual* ]]
}

step_desktop() {
  CHANGED=0
  # Wayland off: DCV console sessions capture an X display (black screen under Wayland, Ubuntu 22.04+).
  # Auto-login: the console opens on the viewer; DCV itself still asks for the password.
  write_file /etc/gdm3/custom.conf 0644 <<CONF
# Managed by so101-twin bootstrap.sh (rewritten when it differs).
[daemon]
WaylandEnable=false
AutomaticLoginEnable=true
AutomaticLogin=${DESKTOP_USER}

[security]

[xdmcp]

[chooser]

[debug]
CONF
  # Defaults for every user: no blanking, no lock, no suspend; the viewer is watched, not typed at.
  write_file /usr/share/glib-2.0/schemas/90_so101-twin.gschema.override 0644 <<'GSCHEMA'
# Managed by so101-twin bootstrap.sh: a kiosk-like desktop for the twin viewer.
[org.gnome.desktop.session]
idle-delay=0

[org.gnome.desktop.screensaver]
lock-enabled=false
idle-activation-enabled=false

[org.gnome.desktop.lockdown]
disable-lock-screen=true

[org.gnome.settings-daemon.plugins.power]
sleep-inactive-ac-type='nothing'
sleep-inactive-battery-type='nothing'
idle-dim=false
GSCHEMA
  if [ "$CHANGED" = 1 ]; then
    glib-compile-schemas "$ROOT/usr/share/glib-2.0/schemas"
    DISPLAY_CHANGED=1
  fi
  # Crash-report pop-ups would cover the viewer too.
  write_file /etc/default/apport 0644 <<'APPORT'
# Managed by so101-twin bootstrap.sh: no crash-report dialogs on the twin desktop.
enabled=0
APPORT
  # GNOME's first-run wizard is skipped when this file exists; ~/.config must be the user's own, or
  # GNOME cannot save any setting (everything here is written by root).
  write_file "/home/${DESKTOP_USER}/.config/gnome-initial-setup-done" 0644 <<<"yes"
  chown -R "$DESKTOP_USER:" "$ROOT/home/${DESKTOP_USER}/.config"

  if [ "$GPU" = 1 ]; then
    if ! xorg_conf_ok; then
      command -v nvidia-xconfig >/dev/null 2>&1 || apt_install nvidia-xconfig
      # nvidia-xconfig edits a legacy XF86Config instead of writing xorg.conf when one exists.
      rm -f "$ROOT"/etc/X11/XF86Config*
      nvidia-xconfig --preserve-busid --enable-all-gpus --allow-empty-initial-configuration \
        --virtual="$VIRTUAL_SCREEN" --output-xconfig="${ROOT}${XORG_CONF}"
      xorg_conf_ok || die "nvidia-xconfig wrote ${XORG_CONF} without the nvidia driver, a virtual screen or AllowEmptyInitialConfiguration"
      log "xorg.conf: NVIDIA, virtual screen ${VIRTUAL_SCREEN}, starts without a monitor"
      DISPLAY_CHANGED=1
    fi
  else
    CHANGED=0
    write_file "$XORG_CONF" 0644 <<'XORG'
# Managed by so101-twin bootstrap.sh: no GPU, so the console session gets a dummy screen.
Section "Device"
    Identifier "DummyDevice"
    Driver "dummy"
    VideoRam 512000
EndSection

Section "Monitor"
    Identifier "DummyMonitor"
    HorizSync 5.0 - 1000.0
    VertRefresh 5.0 - 200.0
EndSection

Section "Screen"
    Identifier "DummyScreen"
    Device "DummyDevice"
    Monitor "DummyMonitor"
    DefaultDepth 24
    SubSection "Display"
        Depth 24
        Virtual 4096 2160
    EndSubSection
EndSection
XORG
    [ "$CHANGED" = 0 ] || DISPLAY_CHANGED=1
  fi
}

# --- the desktop user's password = the DCV login (never traced, never logged, never in UserData) -----
step_password() {
  local stamp="$STATE/password.version" version secret
  version="$(aws secretsmanager describe-secret --region "$AWS_REGION" --secret-id "$DCV_SECRET_ARN" \
    --query 'VersionIdsToStages | keys(@) | [0]' --output text)"
  if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$version" ]; then
    return 0
  fi
  secret="$(aws secretsmanager get-secret-value --region "$AWS_REGION" --secret-id "$DCV_SECRET_ARN" \
    --query SecretString --output text)"
  printf '%s:%s\n' "$DESKTOP_USER" "$secret" | chpasswd
  unset secret
  printf '%s\n' "$version" >"$stamp"
  log "password of $DESKTOP_USER set from the DCV password secret"
}

# --- Amazon DCV -------------------------------------------------------------------------------------
install_dcv_packages() {
  local work ubuntu arch tarball debs deb
  work="$(mktemp -d)"
  # shellcheck source=/dev/null
  ubuntu="$(. "$ROOT/etc/os-release" && echo "${VERSION_ID//./}")"
  arch="$(uname -m)"
  tarball="nice-dcv-ubuntu${ubuntu}-${arch}.tgz"
  log "installing DCV from $DCV_CDN/$tarball"
  retry curl -fsSL -o "$work/NICE-GPG-KEY" "$DCV_CDN/NICE-GPG-KEY"
  gpg --import "$work/NICE-GPG-KEY"
  retry curl -fsSL -o "$work/$tarball" "$DCV_CDN/$tarball"
  tar -xzf "$work/$tarball" -C "$work"
  # The tarball unpacks to one versioned directory; find the packages with a glob after extracting
  # (listing the archive and stopping after its first line would kill tar with SIGPIPE under pipefail).
  debs=("$work"/nice-dcv-*/nice-dcv-server_*.deb "$work"/nice-dcv-*/nice-dcv-web-viewer_*.deb)
  for deb in "${debs[@]}"; do
    [ -f "$deb" ] || die "$tarball has no ${deb##*/} (its layout changed?)"
  done
  retry apt-get "${APT_OPTS[@]}" install -y -q "${debs[@]}"
  rm -rf "$work"
}

step_dcv() {
  local groups
  if ! installed nice-dcv-server || ! installed nice-dcv-web-viewer; then
    install_dcv_packages
    DISPLAY_CHANGED=1
  fi
  groups="$(id -nG dcv)"
  [[ " $groups " == *" video "* ]] || usermod -aG video dcv
  CHANGED=0
  write_file /etc/dcv/dcv.conf 0644 <<CONF
# Managed by so101-twin bootstrap.sh (rewritten when it differs).
[license]

[log]

[session-management]
create-session = true

[session-management/automatic-console-session]
owner = "${DESKTOP_USER}"

[display]
web-client-max-head-resolution = (${VIRTUAL_SCREEN%x*}, ${VIRTUAL_SCREEN#*x})

[connectivity]
web-port = 8443
quic-port = 8443
enable-quic-frontend = true

[security]
authentication = "system"
CONF
  [ "$CHANGED" = 0 ] || DISPLAY_CHANGED=1
  systemctl enable dcvserver
}

# --- display: X first, then DCV, then the console session -------------------------------------------
x_ready() {
  if [ "$GPU" = 1 ]; then check_x_on_gpu; else pgrep -x Xorg >/dev/null; fi
}

step_display() {
  [ "$(systemctl get-default)" = graphical.target ] || systemctl set-default graphical.target
  if [ "$MODE" = boot ] || [ "$DISPLAY_CHANGED" = 1 ] || ! x_ready; then
    log "(re)starting GDM so X starts with the current xorg.conf and auto-login"
    systemctl restart gdm3
    wait_for "$WAIT_X_TRIES" 5 "X on the GPU" x_ready || die "X did not start on the GPU: $DETAIL"
    # DCV attaches its console session to the X display that runs when it starts.
    systemctl restart dcvserver
  elif ! systemctl is-active --quiet dcvserver; then
    systemctl restart dcvserver
  fi
  log "X: $DETAIL"
  if ! wait_for "$WAIT_DCV_TRIES" 5 "the DCV console session" check_dcv_session; then
    log "no automatic console session ($DETAIL); creating it"
    dcv create-session --type=console --owner "$DESKTOP_USER" console
    wait_for 12 5 "the DCV console session" check_dcv_session || die "DCV console session: $DETAIL"
  fi
}

# --- verify: the twin works -----------------------------------------------------------------------
step_verify() {
  local failures=()
  wait_for "$WAIT_X_TRIES" 5 "X on the GPU" x_ready || failures+=("x-on-gpu: $DETAIL")
  log "x-on-gpu: $DETAIL"
  wait_for "$WAIT_DCV_TRIES" 5 "the DCV console session" check_dcv_session || failures+=("dcv-session: $DETAIL")
  log "dcv-session: $DETAIL"
  wait_for "$WAIT_AGENT_TRIES" 5 "the agent subscribed" check_agent || failures+=("agent: $DETAIL")
  log "agent: $DETAIL"
  log "telemetry: ${TELEMETRY_RESULT#*$'\t'} (not required: no arm needs to be publishing)"
  wait_for "$WAIT_VIEWER_TRIES" 5 "the viewer" check_viewer || failures+=("viewer: $DETAIL")
  log "viewer: $DETAIL"
  if [ ${#failures[@]} -gt 0 ]; then
    die "$(printf '%s; ' "${failures[@]}")"
  fi
}

main() {
  log "$MODE of deployment $DEPLOYMENT_VERSION (settings $DEPLOYMENT)"
  run_step logs step_logs
  run_step packages step_packages
  run_step gpu step_gpu
  run_step agent step_agent
  run_step desktop step_desktop
  run_step password step_password
  run_step dcv step_dcv
  run_step display step_display
  run_step verify step_verify
  STEP=finish
  finish SUCCESS "deployment $DEPLOYMENT_VERSION verified: X on the GPU, DCV console session of $DESKTOP_USER, agent subscribed, viewer running"
  log "done: deployment $DEPLOYMENT_VERSION"
}

main
