#!/usr/bin/env bash
# Sets up the so101-twin host and proves it works; started by the UserData (user-data.sh) with the
# deployment settings it read from the stack's SSM parameter:
#   bash bootstrap.sh /etc/so101-twin/deployment.env
# Steps, in order (docs/host.md has the timeline and why each differs from AWS's DCV recipe):
#   settings  the deployment parameter's allowed keys, all present
#   apt       unattended-upgrades and the apt timers stopped and masked for the run; the dpkg lock free
#   logs      the CloudWatch agent (signature checked) shipping this log from its first line, and the others
#   packages  GNOME (ubuntu-desktop-minimal) and GDM with their recommends (Xorg.wrap), mesa-utils, ...,
#             and Firefox (a snap) for the operator console's launcher
#   gpu       the NVIDIA driver (none: FAILURE), and its Xorg module only if the packaged one matches
#   agent     install-agent.sh: its own user, locked requirements with hashes, sandboxed service, viewer
#   desktop   GDM (Xorg, auto-login), Xorg.wrap with root rights, a quiet GNOME, no admin rights for the
#             desktop user, xorg.conf for a monitor-less GPU (virtual screen, AllowEmptyInitialConfiguration)
#   password  the desktop user's password (the DCV login): the secret's AWSCURRENT version
#   dcv       Amazon DCV server + web viewer: pinned release, tarball SHA-256 and package signatures checked
#   display   X (GDM) first, then DCV, then the console session; the same order on every later start
#   verify    host-check.sh: X on the GPU, the console session, the agent subscribed, the viewer stable for
#             20 s, and a screenshot of the console that is not one flat colour
#   alarms    the AgentSilent alarm's actions turned on (created off, so the install does not page)
# First boot (SO101_TWIN_MODE=boot) ends by signalling CloudFormation: SUCCESS after alarms, FAILURE from
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
RELEASES="$HERE/releases.env"
XORG_CONF=/etc/X11/xorg.conf
DCV_CDN=https://d1uj6qtbmh3dt5.cloudfront.net
CLOUDWATCH_KEY_URL=https://amazoncloudwatch-agent.s3.amazonaws.com/assets/amazon-cloudwatch-agent.gpg
START_UNIT=/etc/systemd/system/so101-twin-start.service
# The host's own logs, rotated every hour (step_logs); the state file beside the boot's own state.
ROTATE_UNIT=so101-twin-logrotate
ROTATE_CONF=/etc/so101-twin/logrotate.conf
ROTATE_STATE=/var/lib/so101-twin/logrotate.status
# The largest screen a DCV web client may ask for (dcv.conf) and the X screen's virtual size: with no
# monitor attached the NVIDIA driver has no mode to start from, so X needs the size given.
VIRTUAL_SCREEN=4096x2160
# The dpkg lock, polled every 5 s once automatic updates are stopped: 5 minutes at most.
WAIT_LOCK_TRIES=60

if [ -z "${SO101_TWIN_LOGGING:-}" ]; then
  mkdir -p "$(dirname "$LOG")"
  exec > >(tee -a "$LOG") 2>&1
  export SO101_TWIN_LOGGING=1
fi
mkdir -p "$STATE"

export DEBIAN_FRONTEND=noninteractive
STEP=settings
FAIL_DETAIL=""
DISPLAY_CHANGED=0
# Set when only DCV's own configuration changed (dcv.conf, its unit's drop-in): DCV alone is restarted, and
# attaches its console session to the X that runs; GDM's restart would end the desktop and its viewer.
DCV_CHANGED=0

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
    curl -fsS --max-time 30 --retry 3 -X PUT -H 'Content-Type:' --data-binary "$body" "$SO101_TWIN_HANDLE" ||
      log "could not post to the wait condition (it may be complete already)"
  fi
  aws cloudformation signal-resource --region "${AWS_REGION:-${SO101_TWIN_REGION:-}}" \
    --stack-name "$SO101_TWIN_STACK" --logical-resource-id "${SO101_TWIN_RESOURCE:-}" \
    --unique-id "$instance" --status "$status" "${AWS_LIMITS[@]}" ||
    log "signal-resource $status failed"
  log "signalled $status to $SO101_TWIN_STACK/${SO101_TWIN_RESOURCE:-}"
}

# finish STATUS SUMMARY: give apt its timers back, record the outcome on the host; on the first boot, signal.
finish() {
  local status="$1" summary="$2" tail_text
  restore_apt "$STATE" || log "could not restore the apt timers (the next start's checks retry)"
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
# The user name reaches paths, config files and commands.
[[ $DESKTOP_USER =~ ^[a-z_][a-z0-9_-]{0,31}$ ]] || die "DESKTOP_USER=$DESKTOP_USER is not a Linux user name"
URL_SUFFIX="${URL_SUFFIX:-amazonaws.com}"

# The pins of userdata/releases.env (shipped with these scripts, as trusted as they are): its DCV_* and
# CLOUDWATCH_* keys.
load_releases() {
  local keys=() line
  while IFS= read -r line; do
    if [[ $line =~ ^((DCV|CLOUDWATCH)_[A-Z0-9_]+)= ]]; then keys+=("${BASH_REMATCH[1]}"); fi
  done <"$RELEASES"
  [ ${#keys[@]} -gt 0 ] || die "$RELEASES pins nothing"
  load_env "$RELEASES" "${keys[@]}"
}

run_step() {
  local t0=$SECONDS
  STEP="$1"
  shift
  log "step $STEP: start"
  "$@"
  log "step $STEP: done in $((SECONDS - t0)) s"
}

# --- apt: nothing else may take the dpkg lock while the boot installs ----------------------------------
step_apt() {
  hold_apt "$STATE"
  wait_for "$WAIT_LOCK_TRIES" 5 "the dpkg lock" dpkg_lock_free ||
    die "the dpkg lock is still held by $LOCK_HOLDER after $((WAIT_LOCK_TRIES * 5)) s with automatic updates" \
      "stopped: see what it is (ps -fp <pid>; journalctl -u apt-daily-upgrade), let it finish, run the update again"
}

# --- logs: to CloudWatch from the first step ------------------------------------------------------
install_cloudwatch_agent() {
  local work arch base problem
  work="$(mktemp -d)"
  arch="$(dpkg --print-architecture)"
  # The regional bucket, partition-aware through the URL suffix (amazonaws.com, amazonaws.com.cn).
  base="https://amazoncloudwatch-agent-${AWS_REGION}.s3.${AWS_REGION}.${URL_SUFFIX}/ubuntu/${arch}/latest"
  download "$base/amazon-cloudwatch-agent.deb" "$work/amazon-cloudwatch-agent.deb" 300
  download "$base/amazon-cloudwatch-agent.deb.sig" "$work/amazon-cloudwatch-agent.deb.sig"
  download "$CLOUDWATCH_KEY_URL" "$work/amazon-cloudwatch-agent.gpg"
  problem="$(verify_detached "$work/amazon-cloudwatch-agent.gpg" "$CLOUDWATCH_KEY_FINGERPRINT" \
    "$work/amazon-cloudwatch-agent.deb.sig" "$work/amazon-cloudwatch-agent.deb" 2>&1)" ||
    die "the CloudWatch agent package failed its signature check, not installed: $problem"
  log "CloudWatch agent package: signature by $CLOUDWATCH_KEY_FINGERPRINT verified"
  retry apt-get "${APT_OPTS[@]}" install -y -q "$work/amazon-cloudwatch-agent.deb"
  rm -rf "$work"
}

step_logs() {
  local ctl="$ROOT/opt/aws/amazon-cloudwatch-agent/bin/amazon-cloudwatch-agent-ctl"
  load_releases
  [ -n "${CLOUDWATCH_KEY_FINGERPRINT:-}" ] || die "$RELEASES pins no CLOUDWATCH_KEY_FINGERPRINT"
  if [ ! -x "$ctl" ]; then
    install_cloudwatch_agent
    [ -x "$ctl" ] || die "the CloudWatch agent package did not install $ctl"
  fi
  CHANGED=0
  # rsyslog copies the agent's journal lines to a file the CloudWatch agent can follow, and with them the
  # lines of the savers of agent.local.toml and of the alarm state (install-agent.sh): a copy that could not
  # be saved is seen there.
  write_file /etc/rsyslog.d/30-so101-twin.conf 0644 <<'RSYSLOG'
# Managed by so101-twin bootstrap.sh: the agent's log as a file for the CloudWatch agent.
:programname, isequal, "so101-twin-agent" /var/log/so101-twin-agent.log
:programname, isequal, "so101-twin-local-config" /var/log/so101-twin-agent.log
:programname, isequal, "so101-twin-alarm-state" /var/log/so101-twin-agent.log
RSYSLOG
  # rsyslog ships with Ubuntu server images; the packages step installs it otherwise and it reads the rule then.
  if [ "$CHANGED" = 1 ] && installed rsyslog; then systemctl restart rsyslog; fi
  CHANGED=0
  # logrotate's own timer runs once a day, and judges maxsize only then: an agent logging an error flood
  # could write gigabytes before it. Ours runs every hour with a state file of its own, its config outside
  # /etc/logrotate.d so that the daily run does not rotate the same files on a second state.
  rm -f "${ROOT}/etc/logrotate.d/so101-twin"
  write_file "$ROTATE_CONF" 0644 <<ROTATE
# Managed by so101-twin bootstrap.sh: bound the host's own logs on disk (CloudWatch keeps them a year).
# Run every hour by ${ROTATE_UNIT}.timer; a log is rotated weekly, or at the first run it is over maxsize.
# As Ubuntu's /etc/logrotate.conf says for its own files: /var/log is group-writable (root:syslog 0775), and
# logrotate refuses every file under such a directory unless told whom to rotate as.
su root adm
/var/log/so101-twin-bootstrap.log /var/log/so101-twin-agent.log ${START_LOG} ${HOST_EMF_FILE} {
  weekly
  rotate 4
  maxsize 50M
  compress
  missingok
  notifempty
  copytruncate
}
ROTATE
  write_file "/etc/systemd/system/${ROTATE_UNIT}.service" 0644 <<UNIT
# Managed by so101-twin bootstrap.sh.
[Unit]
Description=so101-twin: rotate the host's own logs (${ROTATE_CONF})

[Service]
Type=oneshot
ExecStart=/usr/sbin/logrotate --state ${ROTATE_STATE} ${ROTATE_CONF}
Nice=19
IOSchedulingClass=idle
UNIT
  write_file "/etc/systemd/system/${ROTATE_UNIT}.timer" 0644 <<UNIT
# Managed by so101-twin bootstrap.sh.
[Unit]
Description=so101-twin: rotate the host's own logs every hour

[Timer]
OnCalendar=hourly
RandomizedDelaySec=5min

[Install]
WantedBy=timers.target
UNIT
  if [ "$CHANGED" = 1 ]; then systemctl daemon-reload; fi
  systemctl enable --now "${ROTATE_UNIT}.timer" >/dev/null 2>&1
  CHANGED=0
  # The agent's Embedded Metric Format lines: CloudWatch Logs turns each into the SO101Twin metrics the
  # stack's alarms watch (agents/twin/output/emf.py, stacks/monitoring.py); the host checks after each start
  # write theirs to a file of their own.
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
  {"file_path": "${START_LOG}", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/start"},
  {"file_path": "${HOST_EMF_FILE}", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/host-emf"},
  {"file_path": "${EMF_FILE}", "log_group_name": "${LOG_GROUP}",
   "log_stream_name": "{instance_id}/emf"}]}}}}
JSON
  if [ "$CHANGED" = 1 ] || ! systemctl is-active --quiet amazon-cloudwatch-agent; then
    "$ctl" -a fetch-config -m ec2 -s -c "file:/opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json"
  fi
}

# --- packages -------------------------------------------------------------------------------------
step_packages() {
  # The desktop with its recommends, as AWS's recipes install it: among them xserver-xorg-legacy, whose
  # Xorg.wrap lets GDM start X with root rights, which NVIDIA's driver without kernel modesetting needs.
  # Named here too, so a host whose desktop was installed without recommends gets it on its next update.
  apt_install --recommends ubuntu-desktop-minimal gdm3 xserver-xorg-legacy
  # dpkg-dev: the DCV server's postinst calls dpkg-architecture. python3.12-venv: the agent's venv.
  # binutils (ar) and gnupg: the signature checks of the DCV packages. mesa-utils (glxinfo) and x11-utils
  # (xwininfo): the host checks ask X what renders OpenGL and where the viewer's window is. logrotate: the
  # logs step's hourly rotation runs it (Ubuntu's images have it; named so that none goes without).
  apt_install mesa-utils x11-utils dpkg-dev python3.12-venv curl rsyslog binutils gnupg logrotate
  [ -x "$ROOT/usr/lib/xorg/Xorg.wrap" ] ||
    die "xserver-xorg-legacy installed no /usr/lib/xorg/Xorg.wrap: GDM could not start X for the NVIDIA driver"
  install_browser
}

# The desktop's browser, for the operator console's launcher (install-agent.sh). ubuntu-desktop-minimal
# brings none: since Ubuntu 21.10 its recommends no longer name firefox, whose deb is only a stub that
# installs the snap; Ubuntu's installer seeds the snap, which apt never does. So the snap, from the Snap Store
# (snapd checks its signed assertions; the DLAMI's Ubuntu already runs snapd). Its enterprise policies (read
# from /etc/firefox/policies) skip the first-run page and the default-browser question.
install_browser() {
  if ! snap list firefox >/dev/null 2>&1; then
    # On a fresh instance snapd may still be seeding, and an install then fails "too early for operation".
    timeout 900 snap wait system seed.loaded ||
      die "snapd did not finish seeding within 15 min (snap changes says what it waits on): no browser"
    log "snap install firefox (the desktop's browser, for the operator console)"
    retry snap install firefox || die "snap install firefox failed: the console launcher needs a browser"
  fi
  write_file /etc/firefox/policies/policies.json 0644 <<'JSON'
{"policies": {"DontCheckDefaultBrowser": true, "OverrideFirstRunPage": "", "OverridePostUpdatePage": "",
  "DisableTelemetry": true}}
JSON
}

# --- the GPU and the Xorg driver module matching it -----------------------------------------------
nvidia_xorg_module() {
  [ -e "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] ||
    [ -e "$ROOT/usr/lib/aarch64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] ||
    [ -e "$ROOT/usr/lib/xorg/modules/drivers/nvidia_drv.so" ]
}

# Whether the PCI bus shows an NVIDIA device (vendor 0x10de), for the message when the driver is missing.
nvidia_on_pci() {
  local vendor
  for vendor in "$ROOT"/sys/bus/pci/devices/*/vendor; do
    [ -f "$vendor" ] && [ "$(cat "$vendor")" = 0x10de ] && return 0
  done
  return 1
}

# The packaged driver's flavour, e.g. 580-server from libnvidia-gl-580-server; empty when the driver was not
# installed from packages.
nvidia_flavour() {
  local listing pkg status
  listing="$(dpkg-query -W -f='${Package} ${Status}\n' 'libnvidia-gl-*' 2>/dev/null || true)"
  while read -r pkg status; do
    if [ "$status" = "install ok installed" ]; then
      echo "${pkg#libnvidia-gl-}"
      return 0
    fi
  done <<<"$listing"
}

# apt's candidate version of PKG (after apt-get update), empty when apt has none.
apt_candidate() {
  local policy line
  policy="$(apt-cache policy "$1" 2>/dev/null || true)"
  while IFS= read -r line; do
    if [[ $line =~ ^[[:space:]]*Candidate:[[:space:]]*(.+)$ ]]; then
      [ "${BASH_REMATCH[1]}" = "(none)" ] || echo "${BASH_REMATCH[1]}"
      return 0
    fi
  done <<<"$policy"
}

# The NVIDIA Xorg module is missing: Ubuntu's xserver-xorg-video-nvidia-<flavour> pins its libraries to
# exact versions, so it is installed only when it is the very version of the installed driver; any other
# would replace the driver under the running kernel module.
install_matching_xorg_module() {
  local flavour driver candidate
  flavour="$(nvidia_flavour)"
  [ -n "$flavour" ] ||
    die "the NVIDIA Xorg module nvidia_drv.so is missing and the driver is not from Ubuntu packages (no" \
      "libnvidia-gl-*): X cannot use the GPU; use an AMI whose driver includes its Xorg module (the default" \
      "DLAMI Base OSS NVIDIA)"
  driver="$(dpkg-query -W -f='${Version}' "libnvidia-gl-$flavour")"
  retry apt-get "${APT_OPTS[@]}" update -q
  candidate="$(apt_candidate "xserver-xorg-video-nvidia-$flavour")"
  [ "$candidate" = "$driver" ] ||
    die "the NVIDIA Xorg module nvidia_drv.so is missing, and apt offers xserver-xorg-video-nvidia-$flavour" \
      "${candidate:-(none)}, not the installed driver's $driver: installing it would replace the driver." \
      "Use an AMI whose driver includes its Xorg module (the default DLAMI Base OSS NVIDIA)"
  log "the NVIDIA Xorg module is missing; installing xserver-xorg-video-nvidia-$flavour $driver (the driver's own version)"
  apt_install "xserver-xorg-video-nvidia-$flavour"
  nvidia_xorg_module || die "xserver-xorg-video-nvidia-$flavour installed no nvidia_drv.so"
}

step_gpu() {
  local gpus where
  if ! command -v nvidia-smi >/dev/null 2>&1; then
    if nvidia_on_pci; then where="the instance has an NVIDIA GPU (PCI vendor 10de) but"; else
      where="the instance shows no NVIDIA GPU on its PCI bus (a G or P instance type has one), and"
    fi
    die "no NVIDIA driver: $where nvidia-smi is missing. The twin's desktop runs X on the GPU: deploy the" \
      "default DLAMI Base OSS NVIDIA AMI (amiSsmParameter) or an AMI with NVIDIA's driver"
  fi
  gpus="$(nvidia-smi -L)" || die "nvidia-smi -L failed: the NVIDIA driver is not working"
  [[ $gpus == *GPU* ]] || die "nvidia-smi lists no GPU: $gpus"
  log "GPU: ${gpus//$'\n'/; }"
  nvidia_xorg_module || install_matching_xorg_module
}

# --- the agent ------------------------------------------------------------------------------------
step_agent() {
  AGENT_SRC="$ROOT/opt/so101-twin/agent-src" PYTHON="${PYTHON:-python3.12}" AWS_REGION="$AWS_REGION" \
    TOPIC_PREFIX="$TOPIC_PREFIX" DEVICES="$DEVICES" UNITS="$UNITS" CLIENT_ID_PREFIX="$CLIENT_ID_PREFIX" \
    ARM_RATE_HZ="${ARM_RATE_HZ:-10.0}" MAX_CONNECTIONS="${MAX_CONNECTIONS:-8}" \
    DESKTOP_USER="$DESKTOP_USER" RECORD_SESSIONS="${RECORD_SESSIONS:-false}" \
    AGENT_NAME="${AGENT_NAME:-so101-twin}" HISTORY_URI="${HISTORY_URI:-}" ROS2="${ROS2:-false}" \
    CALIBRATIONS_URI="${CALIBRATIONS_URI:-}" HOST_STATE_URI="${HOST_STATE_URI:-}" \
    ALERT_TOPIC_ARN="${ALERT_TOPIC_ARN:-}" \
    ALERT_WARNINGS="${ALERT_WARNINGS:-false}" \
    bash "$HERE/install-agent.sh"
}

# --- desktop: GDM on Xorg with auto-login, a quiet GNOME, X for a monitor-less GPU ----------------
xorg_conf_ok() {
  local text
  text="$(cat "${ROOT}${XORG_CONF}" 2>/dev/null)" || return 1
  [[ $text == *'Driver'*'"nvidia"'* && $text == *AllowEmptyInitialConfiguration* && $text == *Virtual* ]]
}

# The desktop user logs in to DCV with a password: that login must not be root. Ubuntu's cloud images make
# the default user an administrator (sudo without password, and the lxd group); administration goes through
# Session Manager instead, whose ssm-user has sudo.
revoke_admin_rights() {
  local groups group kept file=/etc/sudoers.d/90-cloud-init-users
  groups=" $(id -nG "$DESKTOP_USER") "
  for group in sudo admin lxd docker; do
    if [[ $groups == *" $group "* ]]; then
      gpasswd -d "$DESKTOP_USER" "$group" >/dev/null
      log "removed $DESKTOP_USER from group $group (administration is through Session Manager)"
    fi
  done
  if [ -f "${ROOT}$file" ]; then
    kept="$(grep -v "^${DESKTOP_USER}[[:space:]]" "${ROOT}$file" || true)"
    write_file "$file" 0440 <<<"$kept"
  fi
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
  # Xorg.wrap decides who may start X and with which rights; NVIDIA's driver without kernel modesetting
  # needs root, which its default (auto) grants only for KMS drivers.
  write_file /etc/X11/Xwrapper.config 0644 <<'WRAPPER'
# Managed by so101-twin bootstrap.sh: GDM's X on the NVIDIA GPU runs with root rights (Xorg.wrap).
allowed_users=console
needs_root_rights=yes
WRAPPER
  [ "$CHANGED" = 0 ] || DISPLAY_CHANGED=1
  CHANGED=0
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
  revoke_admin_rights
  # GNOME's first-run wizard is skipped when this file exists; ~/.config must be the user's own, or
  # GNOME cannot save any setting (everything here is written by root).
  write_file "/home/${DESKTOP_USER}/.config/gnome-initial-setup-done" 0644 <<<"yes"
  chown -R "$DESKTOP_USER:" "$ROOT/home/${DESKTOP_USER}/.config"

  if ! xorg_conf_ok; then
    if ! command -v nvidia-xconfig >/dev/null 2>&1; then
      # NVIDIA's driver installs it, though not every packaging does: apt is asked, and else the boot says so.
      { apt_install nvidia-xconfig && command -v nvidia-xconfig >/dev/null 2>&1; } ||
        die "nvidia-xconfig is missing and apt installed none: X cannot be set up for a GPU without a" \
          "monitor. Use an AMI whose NVIDIA driver includes nvidia-xconfig (the default DLAMI Base OSS NVIDIA)"
    fi
    # nvidia-xconfig edits a legacy XF86Config instead of writing xorg.conf when one exists.
    rm -f "$ROOT"/etc/X11/XF86Config*
    nvidia-xconfig --preserve-busid --enable-all-gpus --allow-empty-initial-configuration \
      --virtual="$VIRTUAL_SCREEN" --output-xconfig="${ROOT}${XORG_CONF}"
    xorg_conf_ok || die "nvidia-xconfig wrote ${XORG_CONF} without the nvidia driver, a virtual screen or AllowEmptyInitialConfiguration"
    log "xorg.conf: NVIDIA, virtual screen ${VIRTUAL_SCREEN}, starts without a monitor"
    DISPLAY_CHANGED=1
  fi
}

# --- the desktop user's password = the DCV login (never traced, never logged, never in UserData) -----
# The secret's deletion date ("-" for none) and the version whose stages include AWSCURRENT ("-" for none;
# the map's first key may be AWSPREVIOUS after a change), from describe-secret's JSON on stdin.
SECRET_FIELDS='import json, sys
d = json.load(sys.stdin)
current = [v for v, stages in d.get("VersionIdsToStages", {}).items() if "AWSCURRENT" in stages]
print(d.get("DeletedDate") or "-", current[0] if current else "-")'

# secret_version: the DCV password secret's AWSCURRENT version, into SECRET_VERSION; else the step fails
# with what describe-secret said (its answer and errors hold no secret value, so they are safe to log).
secret_version() {
  local described errors problem fields deleted
  errors="$(mktemp)"
  if ! described="$(aws secretsmanager describe-secret --region "$AWS_REGION" --secret-id "$DCV_SECRET_ARN" \
    --output json "${AWS_LIMITS[@]}" 2>"$errors")"; then
    # The AWS CLI writes its error between newlines: one line, for the step's reason, last-run and the signal
    # (read whole, not through head, which pipefail would fail on a long message).
    problem="$(tr -s '\n' ' ' <"$errors")"
    problem="${problem# }"
    problem="${problem% }"
    problem="${problem:0:300}"
    rm -f "$errors"
    if [[ $problem == *ResourceNotFoundException* ]]; then
      # CloudFormation does not notice a resource deleted behind its back: a plain deploy keeps it gone.
      die "the DCV password secret $DCV_SECRET_ARN no longer exists (describe-secret: $problem): it was" \
        "deleted outside the stack, which cdk deploy does not recreate; cdk destroy then cdk deploy makes" \
        "a new one (docs/deploy.md, Log in)"
    fi
    die "describe-secret of the DCV password secret $DCV_SECRET_ARN failed: $problem (docs/deploy.md, Log in)"
  fi
  rm -f "$errors"
  fields="$(printf '%s' "$described" | python3 -c "$SECRET_FIELDS")" ||
    die "describe-secret of the DCV password secret $DCV_SECRET_ARN answered no JSON secret description"
  read -r deleted SECRET_VERSION <<<"$fields"
  if [ "$deleted" != - ]; then
    die "the DCV password secret $DCV_SECRET_ARN is scheduled for deletion ($deleted, describe-secret's" \
      "DeletedDate): restore it with aws secretsmanager restore-secret --secret-id $DCV_SECRET_ARN," \
      "then run the update"
  fi
  [ "$SECRET_VERSION" != - ] ||
    die "describe-secret of the DCV password secret $DCV_SECRET_ARN lists no AWSCURRENT version"
}

step_password() {
  local stamp="$STATE/password.version" version secret
  secret_version
  version="$SECRET_VERSION"
  if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$version" ]; then
    return 0
  fi
  # As JSON, not `--query SecretString --output text`: for a secret put back as binary that prints "None",
  # which chpasswd would have made the password.
  secret="$(aws secretsmanager get-secret-value --region "$AWS_REGION" --secret-id "$DCV_SECRET_ARN" \
    --version-id "$version" --output json "${AWS_LIMITS[@]}" |
    python3 -c 'import json, sys; s = json.load(sys.stdin).get("SecretString") or sys.exit(1); print(s)')" ||
    die "the DCV password secret's AWSCURRENT version $version holds no text password (binary or empty):" \
      "put one back with aws secretsmanager put-secret-value --secret-string, then run the update"
  printf '%s:%s\n' "$DESKTOP_USER" "$secret" | chpasswd
  unset secret
  printf '%s\n' "$version" >"$stamp"
  log "password of $DESKTOP_USER set from the DCV password secret (AWSCURRENT, version $version)"
}

# --- Amazon DCV -------------------------------------------------------------------------------------
install_dcv_packages() {
  local work ubuntu arch pin_key pin tarball url sha debs deb problem
  if [ -z "${DCV_VERSION:-}" ] || [ -z "${DCV_KEY_FINGERPRINT:-}" ]; then
    die "$RELEASES pins no DCV_VERSION or DCV_KEY_FINGERPRINT"
  fi
  work="$(mktemp -d)"
  # shellcheck source=/dev/null
  ubuntu="$(. "$ROOT/etc/os-release" && echo "${VERSION_ID//./}")"
  arch="$(uname -m)"
  pin_key="DCV_SHA256_UBUNTU${ubuntu}_${arch^^}"
  pin="${!pin_key:-}"
  [ -n "$pin" ] || die "userdata/releases.env pins no DCV tarball for ubuntu${ubuntu}-${arch} ($pin_key):" \
    "add it (docs/host.md, Updating the pinned downloads)"
  tarball="nice-dcv-${DCV_VERSION}-ubuntu${ubuntu}-${arch}.tgz"
  url="$DCV_CDN/${DCV_VERSION%%-*}/Servers/$tarball"
  log "installing DCV $DCV_VERSION from $url"
  download "$url" "$work/$tarball" 600
  sha="$(sha256sum <"$work/$tarball")"
  sha="${sha%% *}"
  [ "$sha" = "$pin" ] || die "$url has SHA-256 $sha, not the pinned $pin: not installed"
  download "$DCV_CDN/NICE-GPG-KEY" "$work/NICE-GPG-KEY"
  tar -xzf "$work/$tarball" -C "$work"
  # The tarball unpacks to one versioned directory; find the packages with a glob after extracting
  # (listing the archive and stopping after its first line would kill tar with SIGPIPE under pipefail).
  debs=("$work"/nice-dcv-*/nice-dcv-server_*.deb "$work"/nice-dcv-*/nice-dcv-web-viewer_*.deb)
  for deb in "${debs[@]}"; do
    [ -f "$deb" ] || die "$tarball has no ${deb##*/} (its layout changed?)"
    problem="$(verify_deb "$work/NICE-GPG-KEY" "$DCV_KEY_FINGERPRINT" "$deb" 2>&1)" ||
      die "DCV package signature check failed, not installed: $problem"
  done
  log "DCV tarball SHA-256 and package signatures by $DCV_KEY_FINGERPRINT verified"
  retry apt-get "${APT_OPTS[@]}" install -y -q "${debs[@]}"
  rm -rf "$work"
}

# The pinned release is installed: nice-dcv-server's version is the release's with a packaging suffix
# (release YEAR.N-BUILD -> package YEAR.N.BUILD-1).
dcv_current() {
  local have
  installed nice-dcv-web-viewer || return 1
  have="$(dpkg-query -W -f='${Version}' nice-dcv-server 2>/dev/null)" || return 1
  [[ $have == "${DCV_VERSION/-/.}"-* ]]
}

step_dcv() {
  local groups idle_timeout="${DCV_IDLE_TIMEOUT:-0}"
  # The stack's dcvIdleTimeoutMinutes (0 without it: a deployment parameter older than the setting).
  if ! [[ $idle_timeout =~ ^[0-9]{1,5}$ ]] || ((10#$idle_timeout > 10080)); then
    die "DCV_IDLE_TIMEOUT=$idle_timeout is not 0..10080 minutes: the stack's dcvIdleTimeoutMinutes"
  fi
  if ! dcv_current; then
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
web-port = ${DCV_PORT}
quic-port = ${DCV_PORT}
enable-quic-frontend = true
# Minutes without input before a client is disconnected (DCV's default 60; 0 never): the twin is watched
# for hours without being touched (the stack's dcvIdleTimeoutMinutes).
idle-timeout = ${idle_timeout}

[security]
authentication = "system"
# DCV locks the OS session when its last client disconnects (default true): the next person would meet
# GNOME's lock screen, not the viewer. GNOME's own lock is off too (disable-lock-screen, step desktop).
os-auto-lock = false
CONF
  # DCV attaches its console session to the X display that runs when it starts: after a reboot it must
  # start after the display manager (so101-twin-start.service then checks that it found X).
  write_file /etc/systemd/system/dcvserver.service.d/10-so101-twin.conf 0644 <<'DROPIN'
# Managed by so101-twin bootstrap.sh: DCV's console session needs the X display GDM starts.
[Unit]
Wants=display-manager.service
After=display-manager.service
DROPIN
  [ "$CHANGED" = 0 ] || DCV_CHANGED=1
  systemctl daemon-reload
  systemctl enable dcvserver
  open_dcv_in_ufw
}

# An AMI that comes with ufw on (the default DLAMI's is off) drops DCV's port after the security group let
# it in: every check on the host would pass while the person's browser met a closed port. AWS's DLAMI sample
# opens the same two when ufw is active. ufw keeps its rules, so this runs once per change.
open_dcv_in_ufw() {
  local status proto
  command -v ufw >/dev/null 2>&1 || return 0
  status="$(ufw status 2>&1)" || die "ufw status failed: ${status:0:300}"
  [[ $status == "Status: active"* ]] || return 0
  for proto in tcp udp; do
    if [[ $status != *"${DCV_PORT}/${proto}"*ALLOW* ]]; then
      ufw allow "${DCV_PORT}/${proto}" >/dev/null
      log "ufw is active: opened ${DCV_PORT}/${proto} for DCV"
    fi
  done
}

# --- display: X first, then DCV, then the console session -------------------------------------------
step_display() {
  [ "$(systemctl get-default)" = graphical.target ] || systemctl set-default graphical.target
  if [ "$MODE" = boot ] || [ "$DISPLAY_CHANGED" = 1 ] || ! check_x_on_gpu; then
    log "(re)starting GDM so X starts with the current xorg.conf and auto-login"
    systemctl restart gdm3
    wait_for "$WAIT_X_TRIES" 5 "X on the GPU" check_x_on_gpu || die "X did not start on the GPU: $DETAIL"
    # DCV attaches its console session to the X display that runs when it starts.
    systemctl restart dcvserver
  elif [ "$DCV_CHANGED" = 1 ] || ! systemctl is-active --quiet dcvserver; then
    systemctl restart dcvserver
  fi
  log "X: $DETAIL"
  ensure_console_session || die "DCV console session: $DETAIL"
  # Every later start: a oneshot after the display manager, DCV and the agent puts the console session on
  # X again if DCV came up first, re-runs the host checks and reports them (host-check.sh --on-start).
  CHANGED=0
  # It waits for network-online.target, which Ubuntu 24.04's systemd-networkd-wait-online holds for up to
  # 2 min when an interface never comes online; AWS's DLAMI sample cuts that wait (to 3 s). 30 s here: the
  # instance's one ENI is up in a few seconds, and the checks after it retry on their own.
  write_file /etc/systemd/system/systemd-networkd-wait-online.service.d/so101-twin.conf 0644 <<'WAIT'
# Managed by so101-twin bootstrap.sh.
[Service]
ExecStart=
ExecStart=/usr/lib/systemd/systemd-networkd-wait-online --timeout=30
WAIT
  write_file "$START_UNIT" 0644 <<UNIT
# Managed by so101-twin bootstrap.sh.
[Unit]
Description=so101-twin: after every start, DCV's console session on X, then the host checks
Wants=network-online.target
After=network-online.target display-manager.service dcvserver.service so101-twin-agent.service

[Service]
Type=oneshot
ExecStart=/bin/bash /opt/so101-twin/userdata/host-check.sh --on-start
SyslogIdentifier=so101-twin-start
TimeoutStartSec=20min

[Install]
WantedBy=graphical.target
UNIT
  if [ "$CHANGED" = 1 ]; then systemctl daemon-reload; fi
  systemctl enable so101-twin-start.service >/dev/null 2>&1
}

# --- verify: the twin works, as a person would see it -----------------------------------------------
step_verify() {
  verify_host || die "$VERIFY_SUMMARY"
}

# --- alarms: a silent agent pages from now on (userdata/lib.sh, arm_silent_alarm) -------------------------
step_alarms() {
  arm_silent_alarm
}

main() {
  log "$MODE of deployment $DEPLOYMENT_VERSION (settings $DEPLOYMENT)"
  run_step apt step_apt
  run_step logs step_logs
  run_step packages step_packages
  run_step gpu step_gpu
  run_step agent step_agent
  run_step desktop step_desktop
  run_step password step_password
  run_step dcv step_dcv
  run_step display step_display
  run_step verify step_verify
  run_step alarms step_alarms
  STEP=finish
  local verified="X on the GPU, DCV console session of $DESKTOP_USER, agent subscribed, viewer stable, the"
  finish SUCCESS "deployment $DEPLOYMENT_VERSION verified: $verified console screenshot shows a desktop"
  log "done: deployment $DEPLOYMENT_VERSION"
}

main
