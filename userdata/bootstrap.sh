#!/usr/bin/env bash
# First-boot setup of the so101-twin host, called by the EC2 UserData with the rendered settings file:
#   bash bootstrap.sh /etc/so101-twin/settings.env
# Installs a GNOME desktop (Wayland off), Amazon DCV with an automatic console session owned by the desktop
# user, that user's password from Secrets Manager, and the agent (install-agent.sh). Every step checks before
# it acts, so running it again (e.g. through SSM after an update) only does what is missing.
set -euo pipefail

SETTINGS="${1:-/etc/so101-twin/settings.env}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG=/var/log/so101-twin-bootstrap.log
MARKER=/var/lib/so101-twin/bootstrap.done
DCV_CDN=https://d1uj6qtbmh3dt5.cloudfront.net

# Everything to the log file and the journal (journalctl -t so101-twin-bootstrap), once.
if [ -z "${SO101_TWIN_LOGGING:-}" ]; then
  export SO101_TWIN_LOGGING=1
  exec > >(tee -a "$LOG" | logger -t so101-twin-bootstrap) 2>&1
fi
log() { echo "bootstrap: $(date -Is) $*"; }
trap 'log "FAILED at line $LINENO (exit $?); see $LOG"' ERR

# shellcheck source=/dev/null
. "$SETTINGS"
: "${AWS_REGION:?} ${DCV_SECRET_ARN:?} ${DESKTOP_USER:?}"
export DEBIAN_FRONTEND=noninteractive

retry() {
  local n
  for n in 1 2 3 4 5; do
    "$@" && return 0
    log "retry $n: $*"
    sleep $((n * 10))
  done
  return 1
}

apt_install() {
  local missing=() pkg
  for pkg in "$@"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  log "apt install ${missing[*]}"
  retry apt-get update -q
  retry apt-get install -y -q --no-install-recommends "${missing[@]}"
}

# --- desktop: GNOME on Xorg (DCV console sessions capture a real X display) ----------------------------
setup_desktop() {
  apt_install ubuntu-desktop-minimal gdm3 mesa-utils dpkg-dev python3.12-venv
  # Wayland gives DCV a black screen on Ubuntu 22.04+/NVIDIA.
  local conf=/etc/gdm3/custom.conf
  if ! grep -q '^WaylandEnable=false' "$conf" 2>/dev/null; then
    if grep -q '^#\?WaylandEnable=' "$conf" 2>/dev/null; then
      sed -i 's/^#\?WaylandEnable=.*/WaylandEnable=false/' "$conf"
    elif grep -q '^\[daemon\]' "$conf" 2>/dev/null; then
      sed -i 's/^\[daemon\]/[daemon]\nWaylandEnable=false/' "$conf"
    else
      printf '[daemon]\nWaylandEnable=false\n' >>"$conf"
    fi
    log "Wayland disabled in $conf"
  fi
  # Log the desktop user straight into GNOME on the console, so the DCV session opens on the twin viewer
  # (DCV itself still asks for the password).
  if ! grep -q "^AutomaticLogin=${DESKTOP_USER}\$" "$conf"; then
    sed -i '/^#\?AutomaticLoginEnable=/d; /^#\?AutomaticLogin=/d' "$conf"
    sed -i "s/^\[daemon\]/[daemon]\nAutomaticLoginEnable=true\nAutomaticLogin=${DESKTOP_USER}/" "$conf"
    log "automatic login of $DESKTOP_USER enabled"
  fi
  [ "$(systemctl get-default)" = graphical.target ] || systemctl set-default graphical.target
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q GPU; then
    if ! grep -qs 'Driver *"nvidia"' /etc/X11/xorg.conf; then
      command -v nvidia-xconfig >/dev/null 2>&1 || apt_install nvidia-xconfig
      nvidia-xconfig --preserve-busid --enable-all-gpus
      log "xorg.conf generated for the NVIDIA GPU"
    fi
  else
    # No GPU (e.g. a cheap test instance): a dummy X driver still gives the console session a screen.
    apt_install xserver-xorg-video-dummy
    if [ ! -f /etc/X11/xorg.conf ]; then
      printf '%s\n' 'Section "Device"' '  Identifier "dummy"' '  Driver "dummy"' '  VideoRam 256000' 'EndSection' \
        'Section "Screen"' '  Identifier "screen"' '  Device "dummy"' '  DefaultDepth 24' \
        '  SubSection "Display"' '    Depth 24' '    Modes "1920x1080"' '  EndSubSection' 'EndSection' \
        >/etc/X11/xorg.conf
      log "dummy xorg.conf written (no GPU)"
    fi
  fi
}

# --- Amazon DCV ------------------------------------------------------------------------------------------
install_dcv() {
  if ! dpkg-query -W -f='${Status}' nice-dcv-server 2>/dev/null | grep -q "install ok installed"; then
    local work ubuntu arch tarball
    work="$(mktemp -d)"
    # shellcheck source=/dev/null
    ubuntu="$(. /etc/os-release && echo "${VERSION_ID//./}")"
    arch="$(uname -m)"
    tarball="nice-dcv-ubuntu${ubuntu}-${arch}.tgz"
    log "installing DCV from $DCV_CDN/$tarball"
    retry curl -fsSL -o "$work/NICE-GPG-KEY" "$DCV_CDN/NICE-GPG-KEY"
    gpg --import "$work/NICE-GPG-KEY"
    retry curl -fsSL -o "$work/$tarball" "$DCV_CDN/$tarball"
    tar -xzf "$work/$tarball" -C "$work"
    local dir
    dir="$(tar -tzf "$work/$tarball" | head -1 | cut -d/ -f1)"
    retry apt-get install -y -q "$work/$dir"/nice-dcv-server_*.deb "$work/$dir"/nice-dcv-web-viewer_*.deb
    rm -rf "$work"
  fi
  id -nG dcv 2>/dev/null | grep -qw video || usermod -aG video dcv
  local conf tmp
  conf=/etc/dcv/dcv.conf
  tmp="$(mktemp)"
  cat >"$tmp" <<CONF
# Managed by so101-twin bootstrap.sh (rewritten when it differs).
[license]

[log]

[session-management]
create-session = true

[session-management/automatic-console-session]
owner = "${DESKTOP_USER}"

[display]
web-client-max-head-resolution = (4096, 2160)

[connectivity]
web-port = 8443
quic-port = 8443
enable-quic-frontend = true

[security]
authentication = "system"
CONF
  if ! cmp -s "$tmp" "$conf"; then
    install -m 0644 "$tmp" "$conf"
    log "dcv.conf written"
    systemctl enable dcvserver >/dev/null 2>&1
    systemctl restart dcvserver || true
  fi
  rm -f "$tmp"
  systemctl enable --now dcvserver >/dev/null 2>&1 || true
}

# --- the desktop user's password = the DCV login (never echoed, never in UserData) -----------------------
set_password() {
  local stamp=/var/lib/so101-twin/password.version version secret
  set +x
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

# --- ship the host's logs to CloudWatch (best effort: the twin works without it) -------------------------
setup_log_shipping() {
  [ -n "${LOG_GROUP:-}" ] || return 0
  # rsyslog copies the agent's journal lines to a file the CloudWatch agent can follow.
  local rule=/etc/rsyslog.d/30-so101-twin.conf
  if command -v rsyslogd >/dev/null 2>&1 && [ ! -f "$rule" ]; then
    printf '%s\n' ':programname, isequal, "so101-twin-agent" /var/log/so101-twin-agent.log' >"$rule"
    systemctl restart rsyslog || true
  fi
  if [ ! -x /opt/aws/amazon-cloudwatch-agent/bin/amazon-cloudwatch-agent-ctl ]; then
    local deb
    deb="$(mktemp --suffix=.deb)"
    if retry curl -fsSL -o "$deb" \
      "https://amazoncloudwatch-agent.s3.amazonaws.com/ubuntu/$(dpkg --print-architecture)/latest/amazon-cloudwatch-agent.deb"; then
      apt-get install -y -q "$deb" || log "CloudWatch agent install failed; logs stay local"
    fi
    rm -f "$deb"
  fi
  [ -x /opt/aws/amazon-cloudwatch-agent/bin/amazon-cloudwatch-agent-ctl ] || return 0
  local cfg=/opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json
  # The agent's Embedded Metric Format lines: CloudWatch Logs turns each into the SO101Twin metrics the
  # stack's alarms watch (agents/twin/output/emf.py, stacks/monitoring.py).
  local EMF_FILE=/var/log/so101-twin/emf.log
  cat >"$cfg" <<JSON
{"logs": {"logs_collected": {"files": {"collect_list": [
  {"file_path": "/var/log/so101-twin-bootstrap.log", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/bootstrap"},
  {"file_path": "/var/log/so101-twin-agent.log", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/agent"},
  {"file_path": "${EMF_FILE}", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/emf"}]}}}}
JSON
  /opt/aws/amazon-cloudwatch-agent/bin/amazon-cloudwatch-agent-ctl -a fetch-config -m ec2 -s -c "file:$cfg" \
    >/dev/null || log "CloudWatch agent did not start; logs stay local"
}

main() {
  log "start (settings $SETTINGS)"
  mkdir -p /var/lib/so101-twin
  apt_install python3.12-venv curl
  ROOT=/ AGENT_SRC=/opt/so101-twin/agent-src PYTHON=python3.12 \
    AWS_REGION="$AWS_REGION" TOPIC_PREFIX="$TOPIC_PREFIX" DEVICES="$DEVICES" UNITS="$UNITS" \
    CLIENT_ID_PREFIX="$CLIENT_ID_PREFIX" DESKTOP_USER="$DESKTOP_USER" AGENT_NAME="${AGENT_NAME:-so101-twin}" \
    HISTORY_URI="${HISTORY_URI:-}" ROS2="${ROS2:-false}" \
    bash "$HERE/install-agent.sh"
  setup_desktop
  set_password
  install_dcv
  setup_log_shipping
  if ! systemctl is-active --quiet gdm3 gdm 2>/dev/null; then
    systemctl isolate graphical.target || true
  fi
  date -Is >"$MARKER"
  log "done; marker $MARKER"
}

main
