"""A stand-in twin host for running the real userdata/ scripts in a test: a temporary root plus stand-ins for
the system tools, first on PATH.

What is real: bash, the scripts themselves (the very text the stack renders into UserData and the State
Manager association), tar on a DCV tarball of realistic size and layout, python3 (venv, pip, zipfile, JSON,
the fcntl lock probe), gpg and ar (every signature check runs for real, against test keys), coreutils (sync
logged on its way), timeout, flock, Pillow on the console capture. What stands in, and why: the tools that
would change this machine or need AWS, a GPU, a display or a package mirror (apt-get, apt-cache, dpkg-query,
dpkg, systemctl, journalctl, nvidia-smi, nvidia-xconfig, glxinfo, xwininfo, ss, dcv, chpasswd, chown, usermod,
useradd, gpasswd, id, ps, pgrep, glib-compile-schemas, snap, aws, curl, sleep). Each stand-in logs its
arguments to `calls.log` and keeps the host's state in SIM (installed packages and snaps, active and masked
units, whether X runs on the GPU and what renders its OpenGL, the DCV sessions, the viewer), and encodes the
dependencies that matter for the order of the boot: X starts on the GPU only with the NVIDIA Xorg module,
Xorg.wrap and an xorg.conf for the nvidia driver; dcvserver creates the automatic console session only if X
runs when it starts; the viewer runs once X runs and the autostart entry and its supervisor exist; a masked
unit does not start; the agent answers /healthz only while its service is active; glxinfo and xwininfo answer
only on :0 with the authority file of X's command line. A file SIM/fail/<tool> makes that stand-in fail (to
test a failing step).

The CDN stand-in (curl) serves files from SIM/cdn: a DCV release whose packages carry dpkg-sig builder
signatures and a CloudWatch agent package with a detached signature, both made here with throw-away keys
(`TestSigner`); the scripts asset of a test deploy pins those keys and that tarball (`release_pins`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import tarfile
import tempfile
import textwrap
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

INSTANCE_ID = "i-0123456789abcdef0"
XORG_PID = "1234"
XORG_ARGS = [
    "/usr/lib/xorg/Xorg",
    "vt2",
    "-displayfd",
    "3",
    "-auth",
    "/run/user/1000/gdm/Xauthority",
    "-nolisten",
    "tcp",
    "-background",
    "none",
    "-noreset",
    "-keeptty",
    "-novtswitch",
    "-verbose",
    "3",
]
BOOT_ID = "6f1c2d3e-4a5b-4c6d-8e9f-0a1b2c3d4e5f"
REGION = "us-east-1"
ACCOUNT = "111111111111"
STACK_NAME = "So101TwinStack"
HANDLE_URL = (
    "https://cloudformation-waitcondition-us-east-1.s3.amazonaws.com/arn%3Aaws%3Acloudformation/handle?sig=x"
)
SECRET_ARN = f"arn:aws:secretsmanager:{REGION}:{ACCOUNT}:secret:HostDcvPassword-AbCdEf"
PASSWORD = "Gener4tedPassw0rdOfTwentyFour"
OLD_PASSWORD = "PreviousPassw0rdNotToBeUsed"
LOG_GROUP = f"/so101-twin/{STACK_NAME}/host"
HISTORY_BUCKET = "so101twinstack-historybucket-0123456789ab"
ALARM_TOPIC_ARN = f"arn:aws:sns:{REGION}:{ACCOUNT}:{STACK_NAME}-MonitoringAlarmTopic-AbCdEf"
DCV_VERSION = "2025.0-20103"
DCV_DIR = f"nice-dcv-{DCV_VERSION}-ubuntu2404-x86_64"
DCV_TARBALL = f"{DCV_DIR}.tgz"
DCV_CDN = "https://d1uj6qtbmh3dt5.cloudfront.net"
CLOUDWATCH_BASE = f"https://amazoncloudwatch-agent-{REGION}.s3.{REGION}.amazonaws.com/ubuntu/amd64/latest"
CLOUDWATCH_KEY_URL = "https://amazoncloudwatch-agent.s3.amazonaws.com/assets/amazon-cloudwatch-agent.gpg"
# member -> (size in bytes, signed): several MB in all, like the real tarball's debs; the two installed
# packages carry builder signatures.
DCV_PACKAGES = {
    f"nice-dcv-server_{DCV_VERSION.replace('-', '.')}-1_amd64.ubuntu2404.deb": (3_000_000, True),
    f"nice-dcv-web-viewer_{DCV_VERSION.replace('-', '.')}-1_amd64.ubuntu2404.deb": (2_000_000, True),
    "nice-xdcv_2025.0.655-1_amd64.ubuntu2404.deb": (1_000_000, False),
    "nice-dcv-gl_2025.0.1158-1_amd64.ubuntu2404.deb": (1_000_000, False),
    "nice-dcv-gltest_2025.0.346-1_amd64.ubuntu2404.deb": (500_000, False),
}
APT_UNITS = (
    "apt-daily.timer",
    "apt-daily-upgrade.timer",
    "apt-daily.service",
    "apt-daily-upgrade.service",
    "unattended-upgrades.service",
)

_COMMON = r"""#!/usr/bin/env bash
# Stand-in for a system tool (tests/infra/hostsim.py).
set -u
me="$(basename "$0")"
printf '%s\n' "$me $*" >>"$SIM/calls.log"
if [ -e "$SIM/fail/$me" ]; then echo "$me: failing on purpose (test)" >&2; exit 1; fi
DCV_PID=2345  # dcvserver's process while it runs
mark() { mkdir -p "$SIM/$1"; : >"$SIM/$1/$2"; }
has() { [ -e "$SIM/$1/$2" ]; }
# X on :0 answers a client (glxinfo, xwininfo) only while it runs, with its Xorg's -auth file in XAUTHORITY:
# x_refuses PREFIX prints the client's error lines, each headed PREFIX, and succeeds when it would refuse.
x_refuses() {
  if ! has state xorg || [ "${DISPLAY:-}" != :0 ]; then
    echo "$1unable to open display \"${DISPLAY:-}\"" >&2; return 0
  fi
  local auth
  auth="$(tr '\0' '\n' <"$ROOT/proc/1234/cmdline" | sed -n '/^-auth$/{n;p;}')"
  if [ "${XAUTHORITY:-}" != "$auth" ]; then
    echo "Authorization required, but no authorization protocol specified" >&2
    echo "$1unable to open display \":0\"" >&2; return 0
  fi
  return 1
}
"""

STANDINS: dict[str, str] = {
    "apt-get": r"""
opts=" "
while [ "${1:-}" = -o ]; do opts+="$2 "; shift 2; done  # -o Option=value
case "${1:-}" in
  update) exit 0 ;;
  install)
    shift
    for a in "$@"; do
      case "$a" in
        -*) continue ;;
        */*)
          base="$(basename "$a")"
          case "$base" in
            *_*.deb) pkg="${base%%_*}" ;;
            *) pkg="$(sed -n 's/^Package: //p' "$a")" ;;
          esac ;;
        *) pkg="$a" ;;
      esac
      [ -n "$pkg" ] || { echo "apt-get: $a is not a package" >&2; exit 100; }
      # dpkg asks what to do with a conffile changed on the host when a new version ships another one, and
      # with no terminal to answer (cloud-init, SSM) fails the package: DCV's dcv.conf, which the boot
      # writes, on an upgrade of nice-dcv-server.
      if [ "$pkg" = nice-dcv-server ] && [ -f "$ROOT/etc/dcv/dcv.conf" ] && has dpkg "$pkg" &&
        [[ $opts != *" Dpkg::Options::=--force-confold "* ]]; then
        echo "Configuration file '/etc/dcv/dcv.conf'" >&2
        echo " ==> Modified (by you or by a script) since installation." >&2
        echo "dpkg: error processing package nice-dcv-server (--install):" >&2
        echo " end of file on stdin at conffile prompt" >&2
        exit 100
      fi
      mark dpkg "$pkg"
      # A package file's version is the second field of its name (name_version_arch.deb).
      case "$a" in
        */*_*_*.deb) base="$(basename "$a")"; base="${base#*_}"; echo "${base%%_*}" >"$SIM/dpkg/$pkg" ;;
      esac
      case "$pkg" in
        amazon-cloudwatch-agent)
          mkdir -p "$ROOT/opt/aws/amazon-cloudwatch-agent/bin"
          cp "$SIM/bin/amazon-cloudwatch-agent-ctl" "$ROOT/opt/aws/amazon-cloudwatch-agent/bin/" ;;
        xserver-xorg-legacy)
          mkdir -p "$ROOT/usr/lib/xorg"; : >"$ROOT/usr/lib/xorg/Xorg.wrap"
          chmod 755 "$ROOT/usr/lib/xorg/Xorg.wrap" ;;
        xserver-xorg-video-nvidia-*)
          mkdir -p "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg"
          : >"$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ;;
        nice-dcv-server) mark users dcv; echo "dcv" >"$SIM/groups/dcv"; mkdir -p "$ROOT/etc/dcv" ;;
        gdm3) mkdir -p "$ROOT/etc/gdm3" ;;
      esac
    done ;;
  *) echo "apt-get stand-in: unsupported $*" >&2; exit 100 ;;
esac
""",
    "apt-cache": r"""
# apt-cache policy PKG
[ "$1" = policy ] || { echo "apt-cache stand-in: unsupported $*" >&2; exit 1; }
echo "$2:"
echo "  Installed: (none)"
echo "  Candidate: $(cat "$SIM/apt-candidate/$2" 2>/dev/null || echo '(none)')"
""",
    "dpkg-query": r"""
# dpkg-query -W -f=FORMAT PATTERN
format="${2#-f=}"; pattern="$3"
if [ "$format" = '${Status}' ]; then
  if has dpkg "$pattern"; then printf 'install ok installed'; exit 0; fi
  echo "dpkg-query: no packages found matching $pattern" >&2; exit 1
fi
if [ "$format" = '${Version}' ]; then
  has dpkg "$pattern" || { echo "dpkg-query: no packages found matching $pattern" >&2; exit 1; }
  cat "$SIM/dpkg/$pattern"; exit 0
fi
found=0
for f in "$SIM"/dpkg/*; do
  [ -e "$f" ] || continue
  pkg="$(basename "$f")"
  # shellcheck disable=SC2053
  if [[ $pkg == $pattern ]]; then printf '%s install ok installed\n' "$pkg"; found=1; fi
done
[ "$found" = 1 ] || { echo "dpkg-query: no packages found matching $pattern" >&2; exit 1; }
""",
    "dpkg": r"""[ "${1:-}" = --print-architecture ] && echo amd64""",
    "systemctl": r"""
args=("$@"); quiet=0; runtime=0
[ "${args[0]}" = --global ] && args=("${args[@]:1}")
rest=()
for a in "${args[@]:1}"; do
  case "$a" in
    --quiet) quiet=1 ;; --runtime) runtime=1 ;; --no-block) ;; -p|--value) rest+=("$a") ;; *) rest+=("$a") ;;
  esac
done
verb="${args[0]}"
x_can_start() {
  [ -e "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] &&
    [ -x "$ROOT/usr/lib/xorg/Xorg.wrap" ] &&
    grep -qs 'Driver.*"nvidia"' "$ROOT/etc/X11/xorg.conf" &&
    grep -qs AllowEmptyInitialConfiguration "$ROOT/etc/X11/xorg.conf"
}
start_unit() {
  local unit="${1%.service}"
  if has masked "$unit"; then echo "Failed to start $unit: Unit $unit is masked." >&2; exit 1; fi
  mark services "$unit"
  case "$unit" in
    gdm3)
      rm -f "$SIM/state/xorg" "$SIM/state/viewer"
      if x_can_start; then
        mark state xorg
        if [ -e "$ROOT/home/ubuntu/.config/autostart/so101-twin-view.desktop" ] &&
           [ -x "$ROOT/opt/so101-twin/bin/twin-view-supervised" ]; then mark state viewer; fi
      fi ;;
    dcvserver)
      rm -f "$SIM/state/console"
      # Its process, in its unit's cgroup as systemd puts it (what the DCV port check asks of a listener).
      mkdir -p "$ROOT/proc/$DCV_PID"; echo "0::/system.slice/dcvserver.service" >"$ROOT/proc/$DCV_PID/cgroup"
      if has state xorg && grep -qs '^create-session = true' "$ROOT/etc/dcv/dcv.conf"; then
        sed -n 's/^owner = "\(.*\)"/\1/p' "$ROOT/etc/dcv/dcv.conf" >"$SIM/state/console"
      fi ;;
  esac
}
case "$verb" in
  daemon-reload|enable) ;;
  get-default) cat "$SIM/default.target" 2>/dev/null || echo multi-user.target ;;
  set-default) echo "${rest[0]}" >"$SIM/default.target" ;;
  is-active)
    unit="${rest[0]%.service}"
    if has services "$unit"; then [ "$quiet" = 1 ] || echo active; exit 0; fi
    [ "$quiet" = 1 ] || echo inactive; exit 3 ;;
  show)
    # systemctl show UNIT -p ExecMainStatus --value
    unit="${rest[0]%.service}"; cat "$SIM/exit-status/$unit" 2>/dev/null || echo 0 ;;
  restart|start) for u in "${rest[@]}"; do start_unit "$u"; done ;;
  stop) for u in "${rest[@]}"; do rm -f "$SIM/services/${u%.service}"; done ;;
  mask)
    for u in "${rest[@]}"; do u="${u%.service}"; mark masked "$u"; echo "$runtime" >"$SIM/masked/$u"; done ;;
  unmask) for u in "${rest[@]}"; do rm -f "$SIM/masked/${u%.service}"; done ;;
  *) echo "systemctl stand-in: unsupported ${args[*]}" >&2; exit 1 ;;
esac
""",
    "journalctl": r"""
# journalctl -u UNIT ...: the unit's recorded journal, if the test gave one.
unit=""; while [ $# -gt 0 ]; do [ "$1" = -u ] && unit="${2%.service}"; shift; done
cat "$SIM/journal/$unit" 2>/dev/null || true
""",
    "ufw": r"""
# ufw status | ufw allow PORT/PROTO: inactive unless SIM/ufw-active exists (the default DLAMI's is off).
case "${1:-}" in
  status)
    if [ ! -e "$SIM/ufw-active" ]; then echo "Status: inactive"; exit 0; fi
    echo "Status: active"; echo; echo "To                         Action      From"
    echo "--                         ------      ----"; echo "22/tcp                     ALLOW       Anywhere"
    for rule in "$SIM"/ufw-rules/*; do
      [ -e "$rule" ] && echo "$(basename "$rule" | tr _ /)                   ALLOW       Anywhere"
    done
    exit 0 ;;
  allow) mkdir -p "$SIM/ufw-rules"; : >"$SIM/ufw-rules/${2//\//_}"; echo "Rule added" ;;
  *) echo "ufw stand-in: unsupported $*" >&2; exit 1 ;;
esac
""",
    "pgrep": r"""
# pgrep -x Xorg | pgrep -u USER -f PATTERN
if [ "$1" = -x ] && [ "$2" = Xorg ]; then has state xorg && { echo 1234; exit 0; }; exit 1; fi
if [ "$1" = -u ]; then
  has state viewer || exit 1
  if [ "$(cat "$SIM/viewer-mode" 2>/dev/null)" = crashloop ]; then
    # A viewer that dies every few seconds: its supervisor has started a new one each time we look.
    n=$(( $(cat "$SIM/viewer-starts" 2>/dev/null || echo 0) + 1 )); echo "$n" >"$SIM/viewer-starts"
    echo $((3000 + n)); exit 0
  fi
  echo 2345; exit 0
fi
exit 1
""",
    "ps": r"""
# ps -o etimes= -p PID: seconds the process has run.
pid="${!#}"
case "$pid" in
  2345) cat "$SIM/viewer-age" 2>/dev/null || echo 120 ;;
  3*) echo 3 ;;
  *) exit 1 ;;
esac
""",
    "nvidia-smi": r"""
case "${1:-}" in
  -L) echo "GPU 0: NVIDIA L40S (UUID: GPU-00000000-1111-2222-3333-444444444444)" ;;
  --query-gpu=name,driver_version) echo "NVIDIA L40S, 580.95.05" ;;
  --query-gpu=driver_version) echo "580.95.05" ;;
  "")
    echo "| NVIDIA-SMI 580.95.05    Driver Version: 580.95.05    CUDA Version: 13.0 |"
    echo "| Processes:                                                                |"
    if has state xorg; then echo "|    0   N/A  N/A      1234      G   /usr/lib/xorg/Xorg      4MiB |"; fi ;;
esac
""",
    "glxinfo": r"""
# DISPLAY=:0 XAUTHORITY=FILE glxinfo -B: what renders OpenGL on X. Only X on :0 with its Xorg's -auth file
# answers; SIM/glx holds another renderer's lines (Mesa's llvmpipe: X without NVIDIA's GLX library).
if x_refuses "Error: "; then exit 1; fi
if [ -f "$SIM/glx" ]; then cat "$SIM/glx"; exit 0; fi
echo "name of display: :0"
echo "display: :0  screen: 0"
echo "direct rendering: Yes"
echo "Memory info (GL_NVX_gpu_memory_info):"
echo "    Dedicated video memory: 46068 MB"
echo "OpenGL vendor string: NVIDIA Corporation"
echo "OpenGL renderer string: NVIDIA L40S/PCIe/SSE2"
echo "OpenGL core profile version string: 4.6.0 NVIDIA 580.95.05"
""",
    "xwininfo": r"""
# DISPLAY=:0 XAUTHORITY=FILE xwininfo -root [-tree] | -id ID: X's windows, answered as glxinfo is (only on :0
# with its Xorg's -auth file). The lines are as the real tool prints them (x11-utils 7.7, against Xvfb with
# MuJoCo's viewer open): the screen 1920x1080, the viewer's window where the capture stand-in draws it;
# SIM/xwin-tree holds other windows, SIM/xwin-map/ID a window's map state (IsViewable when absent).
if x_refuses "xwininfo: error: "; then exit 1; fi
if [ "${1:-}" = -id ]; then
  echo ""
  echo "xwininfo: Window id: $2 \"MuJoCo : so101\""
  echo ""
  echo "  Width: 1320"
  echo "  Height: 750"
  echo "  Map State: $(cat "$SIM/xwin-map/$2" 2>/dev/null || echo IsViewable)"
  echo "  Override Redirect State: no"
  exit 0
fi
echo ""
echo "xwininfo: Window id: 0x50d (the root window) (has no name)"
echo ""
if [ "$*" = "-root -tree" ]; then
  echo "  Root window id: 0x50d (the root window) (has no name)"
  echo "  Parent window id: 0x0 (none)"
  if [ -f "$SIM/xwin-tree" ]; then cat "$SIM/xwin-tree"; exit 0; fi
  echo "     2 children:"
  echo "     0x1a00003 (has no name): ()  1332x786+294+144  +294+144"
  echo "        1 child:"
  echo "        0x2200007 \"MuJoCo : so101\": (\"MuJoCo\" \"MuJoCo\")  1320x750+6+30  +300+180"
  echo "     0x200001 (has no name): ()  1x1+0+0  +0+0"
else
  echo "  Absolute upper-left X:  0"
  echo "  Absolute upper-left Y:  0"
  echo "  Width: 1920"
  echo "  Height: 1080"
  echo "  Depth: 24"
fi
""",
    "ss": r"""
# ss -Hltnp | ss -Hlun: listening TCP or UDP sockets, no header, as iproute2 prints them (-p: with the
# processes holding each). dcvserver, while active, listens on 8443 over both (its web and QUIC ports);
# SIM/ss-tcp or SIM/ss-udp replace a listing.
users=""
case "$*" in
  -Hltnp)
    kind=tcp; state=LISTEN; queue="0      10"; users=' users:(("dcvserver",pid='"$DCV_PID"',fd=12))' ;;
  -Hlun) kind=udp; state=UNCONN; queue="0      0" ;;
  *) echo "ss stand-in: only -Hltnp or -Hlun" >&2; exit 1 ;;
esac
resolver=' users:(("systemd-resolve",pid=511,fd=15))'
echo "$state $queue         127.0.0.53%lo:53        0.0.0.0:*${users:+$resolver}"
if [ -f "$SIM/ss-$kind" ]; then cat "$SIM/ss-$kind"; exit 0; fi
if has services dcvserver; then
  echo "$state $queue               0.0.0.0:8443      0.0.0.0:*$users"
  echo "$state $queue                  [::]:8443         [::]:*$users"
fi
""",
    "nvidia-xconfig": r"""
out=/etc/X11/xorg.conf; virtual=""; empty=0
for a in "$@"; do
  case "$a" in
    --output-xconfig=*) out="${a#*=}" ;;
    --virtual=*) virtual="${a#*=}" ;;
    --allow-empty-initial-configuration) empty=1 ;;
  esac
done
mkdir -p "$(dirname "$out")"
{
  echo '# nvidia-xconfig: X configuration file generated by nvidia-xconfig (stand-in)'
  echo 'Section "Device"'; echo '    Identifier     "Device0"'; echo '    Driver         "nvidia"'
  echo '    BusID          "PCI:0:30:0"'
  [ "$empty" = 1 ] && echo '    Option         "AllowEmptyInitialConfiguration" "True"'
  echo 'EndSection'; echo 'Section "Screen"'; echo '    Identifier     "Screen0"'
  echo '    Device         "Device0"'
  echo '    SubSection     "Display"'; echo '        Depth       24'
  [ -n "$virtual" ] && echo "        Virtual     ${virtual%x*} ${virtual#*x}"
  echo '    EndSubSection'; echo 'EndSection'
} >"$out"
""",
    "dcv": r"""
case "$1" in
  list-sessions)
    [ "${2:-}" = --json ] || { echo "dcv stand-in: only list-sessions --json" >&2; exit 2; }
    if has state console; then
      printf '[ { "id" : "console", "owner" : "%s", "name" : "console", "type" : "console",' \
        "$(cat "$SIM/state/console")"
      printf ' "x11-display" : ":0" } ]\n'
    else echo "[ ]"; fi ;;
  create-session)
    has state xorg || { echo "Could not create session: no X server" >&2; exit 1; }
    owner=""
    while [ $# -gt 0 ]; do [ "$1" = --owner ] && owner="$2"; shift; done
    echo "$owner" >"$SIM/state/console" ;;
  get-screenshot)
    has state console || { echo "Could not find session console" >&2; exit 1; }
    out=""; while [ $# -gt 0 ]; do [ "$1" = --output ] && out="$2"; shift; done
    cp "$SIM/screen.png" "$out" ;;
esac
""",
    "glib-compile-schemas": r"""exit 0""",
    "snap": r"""
# snap list NAME | snap install NAME | snap wait system seed.loaded: an installed snap puts its command in
# /snap/bin. A fresh instance's snapd is still seeding: as snapd does, an install before the seeding is done
# fails with "too early for operation", and `snap wait system seed.loaded` returns once it is done.
case "${1:-}" in
  list)
    has snaps "$2" && { echo "Name  Version  Rev"; echo "$2  1.0  1"; exit 0; }
    echo "error: no matching snaps installed" >&2; exit 1 ;;
  wait)
    [ "$*" = "wait system seed.loaded" ] || { echo "snap stand-in: unsupported $*" >&2; exit 1; }
    mark snapd seeded ;;
  install)
    has snapd seeded || {
      echo "error: too early for operation, device not yet seeded or device model not acknowledged" >&2
      exit 1
    }
    mark snaps "$2"; mkdir -p "$ROOT/snap/bin"
    printf '#!/bin/sh\nexit 0\n' >"$ROOT/snap/bin/$2"; chmod 755 "$ROOT/snap/bin/$2" ;;
  *) echo "snap stand-in: unsupported $*" >&2; exit 1 ;;
esac
""",
    "usermod": r"""
# usermod -aG GROUP USER
echo "$2" >>"$SIM/groups/$3"
""",
    "useradd": r"""
user="${!#}"; mark users "$user"; echo "$user" >"$SIM/groups/$user"
""",
    "gpasswd": r"""
# gpasswd -d USER GROUP
grep -vx "$3" "$SIM/groups/$2" >"$SIM/groups/$2.new" || true
mv "$SIM/groups/$2.new" "$SIM/groups/$2"
""",
    "chown": r"""exit 0""",
    # Logged, so a test sees what was flushed, then run for real.
    "sync": r"""exec /usr/bin/sync "$@"
""",
    "sleep": r"""
# SIM/on-sleep: what happens meanwhile (the agent writing a file again), run once.
if [ -x "$SIM/on-sleep" ]; then mv "$SIM/on-sleep" "$SIM/on-sleep.ran"; "$SIM/on-sleep.ran"; fi
exit 0
""",
    "chpasswd": r"""
IFS= read -r line
user="${line%%:*}"; password="${line#*:}"
printf 'chpasswd user=%s password=%s\n' "$user" "$password" >>"$SIM/chpasswd.log"
""",
    "id": r"""
case "$1" in
  -u) has users "$2" && { echo 1000; exit 0; }; echo "id: '$2': no such user" >&2; exit 1 ;;
  -nG)
    has users "$2" || { echo "id: '$2': no such user" >&2; exit 1; }
    tr '\n' ' ' <"$SIM/groups/$2"; echo ;;
esac
""",
    "aws": r"""
case "$1 $2" in
  "ssm get-parameter") cat "$SIM/parameter" ;;
  "s3 cp")
    # The scripts give the options first, then SOURCE DESTINATION: a download, or an upload to s3://.
    # SIM/fail/s3: the bucket refuses this role (what S3 answers then).
    src="${*: -2:1}"; dst="${!#}"
    if [ -e "$SIM/fail/s3" ]; then
      echo "fatal error: An error occurred (403) when calling the HeadObject operation: Forbidden" >&2; exit 1
    fi
    case "$src" in
      s3://*)
        src="${src#s3://}"
        if [ ! -f "$SIM/s3/$src" ]; then
          echo "fatal error: An error occurred (404) when calling the HeadObject operation:" \
            "Key \"$src\" does not exist" >&2
          exit 1
        fi
        cp "$SIM/s3/$src" "$dst" ;;
      *)
        [ -f "$src" ] || { echo "The user-provided path $src does not exist." >&2; exit 255; }
        mkdir -p "$(dirname "$SIM/s3/${dst#s3://}")"
        cp "$src" "$SIM/s3/${dst#s3://}"
        # SIM/on-upload: what happens meanwhile (a person saving a file again), run once.
        if [ -x "$SIM/on-upload" ]; then mv "$SIM/on-upload" "$SIM/on-upload.ran"; "$SIM/on-upload.ran"; fi ;;
    esac ;;
  "s3api list-objects-v2")
    # --bucket B --prefix P --output text and --query KeyCount: how many objects' keys start with P; or
    # --query 'Contents[].[LastModified,Key]': one "<ISO time in UTC>TAB<key>" line per object (a file's
    # mtime stands for LastModified), "None" for none, as the AWS CLI prints them.
    # The CLI's docs: with --output text, a paginated listing's --query may only take what it lists
    # (Contents, CommonPrefixes), so a query of KeyCount needs --no-paginate (one page, as S3 sent it).
    bucket=""; prefix=""; query=""; paginate=1
    while [ $# -gt 0 ]; do
      case "$1" in
        --bucket) bucket="$2"; shift ;; --prefix) prefix="$2"; shift ;; --query) query="$2"; shift ;;
        --no-paginate) paginate=0 ;;
      esac; shift
    done
    if [ "$query" = KeyCount ] && [ "$paginate" = 1 ]; then
      echo "aws stand-in: --query KeyCount --output text on a paginated listing; give --no-paginate" >&2
      exit 2
    fi
    if [ -e "$SIM/fail/s3" ]; then
      echo "An error occurred (AccessDenied) when calling the ListObjectsV2 operation: Access Denied" >&2
      exit 254
    fi
    count=0
    for object in "$SIM/s3/$bucket/$prefix"*; do
      [ -f "$object" ] || continue
      count=$((count + 1))
      if [ "$query" = "Contents[].[LastModified,Key]" ]; then
        printf '%s\t%s\n' "$(date -u -r "$object" +%Y-%m-%dT%H:%M:%S+00:00)" "${object#"$SIM/s3/$bucket/"}"
      fi
    done
    case "$query" in
      KeyCount) echo "$count" ;;
      "Contents[].[LastModified,Key]") [ "$count" -gt 0 ] || echo None ;;
      *) echo "aws stand-in: unsupported --query $query" >&2; exit 2 ;;
    esac ;;
  "secretsmanager describe-secret")
    # SIM/fail/secret-gone: the secret was deleted outside the stack and is past recovery (what AWS answers).
    if [ -e "$SIM/fail/secret-gone" ]; then
      # Between newlines, as the AWS CLI writes an error.
      printf '\n%s %s\n' "An error occurred (ResourceNotFoundException) when calling the DescribeSecret" \
        "operation: Secrets Manager can't find the specified secret." >&2; exit 254
    fi
    # SIM/fail/secret-deleting: the secret is scheduled for deletion (it still answers, with its date).
    if [ -e "$SIM/fail/secret-deleting" ]; then echo '{"DeletedDate": "2026-12-01T10:00:00+00:00",'; else
      echo '{'; fi
    # The map's first key is the previous version: the boot must pick the one staged AWSCURRENT.
    echo ' "Name": "HostDcvPassword",'
    echo ' "VersionIdsToStages": {"v-1": ["AWSPREVIOUS"], "v-2": ["AWSCURRENT"]}}' ;;
  "secretsmanager get-secret-value")
    version=""; while [ $# -gt 0 ]; do [ "$1" = --version-id ] && version="$2"; shift; done
    # SIM/fail/secret: the current version was put back as binary (no SecretString).
    if [ -e "$SIM/fail/secret" ]; then echo '{"SecretBinary": "AAEC"}'; exit 0; fi
    case "$version" in v-2) echo '{"SecretString": "Gener4tedPassw0rdOfTwentyFour"}' ;;
      v-1) echo '{"SecretString": "PreviousPassw0rdNotToBeUsed"}' ;;
      *) echo "aws stand-in: get-secret-value without --version-id" >&2; exit 2 ;; esac ;;
  "cloudformation signal-resource") printf '%s\n' "$*" >>"$SIM/signals.log" ;;
  "cloudwatch enable-alarm-actions")
    # SIM/fail/cloudwatch: the role lacks the right (what CloudWatch answers then).
    if [ -e "$SIM/fail/cloudwatch" ]; then
      echo "An error occurred (AccessDenied) when calling the EnableAlarmActions operation" >&2; exit 254
    fi
    names=""; while [ $# -gt 0 ]; do [ "$1" = --alarm-names ] && names="$2"; shift; done
    [ -n "$names" ] || { echo "aws stand-in: enable-alarm-actions without --alarm-names" >&2; exit 2; }
    printf '%s\n' "$names" >>"$SIM/armed.log" ;;
  *) echo "aws stand-in: unsupported $*" >&2; exit 2 ;;
esac
""",
    "curl": r"""
out=""; method=GET; data=""; url=""
while [ $# -gt 0 ]; do
  case "$1" in
    -o) out="$2"; shift ;;
    -X) method="$2"; shift ;;
    -H|--max-time|--connect-timeout|--retry|--retry-delay|--proto) shift ;;
    --data-binary) data="$2"; shift ;;
    -*) ;;
    *) url="$1" ;;
  esac
  shift
done
[ "$data" = @- ] && data="$(cat)"
emit() { if [ -n "$out" ]; then cat >"$out"; else cat; fi; }
case "$url" in
  https://d1uj6qtbmh3dt5.cloudfront.net/*|https://amazoncloudwatch-agent*)
    name="${url#https://}"; name="${name//\//_}"
    [ -f "$SIM/cdn/$name" ] || { echo "curl: (22) The requested URL returned error: 404" >&2; exit 22; }
    emit <"$SIM/cdn/$name" ;;
  https://cloudformation-waitcondition-*) [ "$method" = PUT ] && printf '%s\n' "$data" >>"$SIM/handle.log" ;;
  */latest/api/token) echo "imds-token" | emit ;;
  */latest/user-data) emit <"$SIM/user-data.sh" ;;
  http://127.0.0.1:8080/*)
    has services so101-twin-agent || { echo "curl: (7) Failed to connect to 127.0.0.1" >&2; exit 7; }
    emit <"$SIM/agent/${url##*/}.json" ;;
  *) echo "curl stand-in: no such URL $url" >&2; exit 22 ;;
esac
""",
    "amazon-cloudwatch-agent-ctl": r"""mark services amazon-cloudwatch-agent""",
}

HEALTHZ = {
    "status": "unavailable",
    "running": True,
    "broker_connected": True,
    "devices": {"arm-001": "OFFLINE"},
    "reasons": ["device arm-001 is OFFLINE"],
}
STATE = {
    "agent": {
        "running": True,
        "topic_filters": ["dt/lerobot/arm-001/telemetry"],
        "broker": {"url": "iot", "connected": True, "subscribes": 1, "messages": 0, "last_error": ""},
    },
    "devices": {
        "arm-001": {"device_id": "arm-001", "health": {"status": "OFFLINE", "age_s": None, "rate_hz": 0.0}}
    },
}


# --- signing, packages and the release they form ------------------------------------------------------------


class TestSigner:
    """A throw-away OpenPGP signing key (ed25519, no passphrase) in its own keyring, driven with real gpg."""

    __test__ = False  # not a pytest class

    def __init__(self, name: str) -> None:
        self.home = Path(tempfile.mkdtemp(prefix="so101-signer-"))
        self._gpg(
            "--passphrase",
            "",
            "--quick-gen-key",
            f"{name} <{name}@example.invalid>",
            "ed25519",
            "sign",
            "never",
        )
        listing = self._gpg("--with-colons", "--fingerprint").stdout.decode()
        self.fingerprint = next(
            line.split(":")[9] for line in listing.splitlines() if line.startswith("fpr:")
        )

    def _gpg(self, *args: str, data: bytes | None = None) -> subprocess.CompletedProcess[bytes]:
        return subprocess.run(
            ["gpg", "--homedir", str(self.home), "--batch", "--quiet", *args],
            input=data,
            capture_output=True,
            check=True,
            timeout=120,
        )

    def public_key(self) -> bytes:
        return self._gpg("--armor", "--export", self.fingerprint).stdout

    def clearsign(self, text: str) -> bytes:
        return self._gpg(
            "--pinentry-mode", "loopback", "--passphrase", "", "--clearsign", data=text.encode()
        ).stdout

    def detach_sign(self, data: bytes) -> bytes:
        return self._gpg("--pinentry-mode", "loopback", "--passphrase", "", "--detach-sign", data=data).stdout

    def close(self) -> None:
        subprocess.run(["gpgconf", "--homedir", str(self.home), "--kill", "all"], check=False, timeout=60)
        shutil.rmtree(self.home, ignore_errors=True)


def _tar_gz(files: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def make_deb(path: Path, package: str, data: bytes, signer: TestSigner | None = None) -> Path:
    """An ar archive laid out like a .deb; with a signer, the `_gpgbuilder` member dpkg-sig writes: a
    clear-signed list of md5, sha1 and size of every other member."""
    members = {
        "debian-binary": b"2.0\n",
        "control.tar.gz": _tar_gz({"./control": f"Package: {package}\nVersion: 1\n".encode()}),
        "data.tar.xz": data,
    }
    work = Path(tempfile.mkdtemp(prefix="so101-deb-"))
    try:
        for name, content in members.items():
            (work / name).write_bytes(content)
        names = list(members)
        if signer is not None:
            lines = "".join(
                f"\t{hashlib.md5(c).hexdigest()} {hashlib.sha1(c).hexdigest()} {len(c)} {n}\n"
                for n, c in members.items()
            )
            text = f"Version: 4\nSigner: \nDate: Mon Nov 23 10:00:00 2026\nRole: builder\nFiles: \n{lines}"
            (work / "_gpgbuilder").write_bytes(signer.clearsign(text))
            names.append("_gpgbuilder")
        path.unlink(missing_ok=True)
        subprocess.run(["ar", "rcD", str(path), *names], cwd=work, check=True, timeout=60)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return path


def make_dcv_tarball(path: Path, signer: TestSigner, seed: int = 101) -> Path:
    """A tarball laid out like AWS's (one versioned directory of .deb files), incompressible, several MB;
    the server and web viewer packages signed by `signer`."""
    rng = random.Random(seed)
    work = Path(tempfile.mkdtemp(prefix="so101-dcv-"))
    try:
        with tarfile.open(path, "w:gz") as tar:
            for name, (size, signed) in DCV_PACKAGES.items():
                deb = make_deb(
                    work / name, name.split("_", 1)[0], rng.randbytes(size), signer if signed else None
                )
                tar.add(deb, arcname=f"{DCV_DIR}/{name}")
            notes = b"DCV release notes (stand-in)\n"
            info = tarfile.TarInfo(f"{DCV_DIR}/README")
            info.size = len(notes)
            tar.addfile(info, io.BytesIO(notes))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return path


def cdn_name(url: str) -> str:
    """The file name the curl stand-in serves `url` from (SIM/cdn/<name>)."""
    return url.removeprefix("https://").replace("/", "_")


def make_cdn(target: Path, dcv_signer: TestSigner, cloudwatch_signer: TestSigner) -> dict[str, Any]:
    """The downloads a boot makes outside apt and PyPI, as files for the CDN stand-in, and their pins."""
    target.mkdir(parents=True, exist_ok=True)
    tarball = make_dcv_tarball(target / cdn_name(f"{DCV_CDN}/2025.0/Servers/{DCV_TARBALL}"), dcv_signer)
    (target / cdn_name(f"{DCV_CDN}/NICE-GPG-KEY")).write_bytes(dcv_signer.public_key())
    agent = b"Package: amazon-cloudwatch-agent\n"
    (target / cdn_name(f"{CLOUDWATCH_BASE}/amazon-cloudwatch-agent.deb")).write_bytes(agent)
    (target / cdn_name(f"{CLOUDWATCH_BASE}/amazon-cloudwatch-agent.deb.sig")).write_bytes(
        cloudwatch_signer.detach_sign(agent)
    )
    (target / cdn_name(CLOUDWATCH_KEY_URL)).write_bytes(cloudwatch_signer.public_key())
    return {
        "dir": target,
        "tarball": tarball,
        "pins": release_pins(
            hashlib.sha256(tarball.read_bytes()).hexdigest(),
            dcv_signer.fingerprint,
            cloudwatch_signer.fingerprint,
        ),
    }


def release_pins(dcv_sha256: str, dcv_key: str, cloudwatch_key: str) -> str:
    """userdata/releases.env as it would pin this release and these keys."""
    return (
        "# Pins of the test release (tests/infra/hostsim.py).\n"
        f"DCV_VERSION={DCV_VERSION}\n"
        f"DCV_SHA256_UBUNTU2404_X86_64={dcv_sha256}\n"
        f"DCV_KEY_FINGERPRINT={dcv_key}\n"
        f"CLOUDWATCH_KEY_FINGERPRINT={cloudwatch_key}\n"
    )


# --- the dependency lock ----------------------------------------------------------------------------------

PROBE = "so101_twin_lock_probe"


def make_probe_wheel(target: Path) -> Path:
    """A tiny real wheel (the lock's stand-in dependency): installing it proves the lock step ran."""
    target.mkdir(parents=True, exist_ok=True)
    wheel = target / f"{PROBE}-1.0-py3-none-any.whl"
    files = {
        f"{PROBE}/__init__.py": b'LOCKED = "from requirements/host.txt"\n',
        f"{PROBE}-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: so101-twin-lock-probe\n"
        b"Version: 1.0\n",
        f"{PROBE}-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: hostsim\nRoot-Is-Purelib: true\n"
        b"Tag: py3-none-any\n",
    }
    record = [f"{name},,{len(data)}" for name, data in files.items()] + [f"{PROBE}-1.0.dist-info/RECORD,,"]
    files[f"{PROBE}-1.0.dist-info/RECORD"] = ("\n".join(record) + "\n").encode()
    # Fixed timestamps: the same bytes every time, so every copy matches the lock's hash.
    with zipfile.ZipFile(wheel, "w") as zf:
        for name, data in files.items():
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
    return wheel


WHEELHOUSE = Path(__file__).resolve().parents[2] / ".wheelhouse"


def lock_wheels(target: Path) -> list[Path]:
    """The wheels a test lock pins, in `target` (the host's --find-links): the probe, the build backend
    (setuptools, wheel) the agent is built with, as the real lock pins its backend, and Pillow, which the
    host's screen check needs (the real lock has it among the agent's dependencies)."""
    backend = [
        wheel
        for pattern in ("setuptools-*.whl", "wheel-*.whl", "pillow-*.whl")
        for wheel in WHEELHOUSE.glob(pattern)
    ]
    if len(backend) < 3:
        raise FileNotFoundError(
            f"{WHEELHOUSE} lacks the setuptools, wheel and pillow wheels: run `make setup`"
        )
    target.mkdir(parents=True, exist_ok=True)
    for wheel in backend:
        shutil.copy(wheel, target / wheel.name)
    return [make_probe_wheel(target), *(target / w.name for w in backend)]


def lock_text(wheels: list[Path]) -> str:
    """A requirements/host.txt pinning `wheels` by hash, in the form of the real lock."""
    lines = ["# lock stand-in (tests/infra/hostsim.py)"]
    for wheel in wheels:
        name, version = wheel.name.split("-")[:2]
        digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
        lines.append(f"{name.replace('_', '-')}=={version} \\\n    --hash=sha256:{digest}")
    return "\n".join(lines) + "\n"


def with_lock(source: Path, target: Path, lock: str) -> Path:
    """A copy of the agent asset `source` whose requirements/host.txt is `lock` (the real lock pins the
    agent's own dependencies, which a test cannot fetch: tests run offline)."""
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
    (target / "requirements").mkdir(exist_ok=True)
    (target / "requirements" / "host.txt").write_text(lock)
    return target


@contextmanager
def dpkg_lock_held(lock: Path) -> Iterator[int]:
    """A process holding `lock` as apt and dpkg hold theirs (an fcntl write lock); yields its pid."""
    script = (
        "import fcntl, sys\n"
        "f = open(sys.argv[1], 'w')\n"
        "fcntl.lockf(f, fcntl.LOCK_EX)\n"
        "print('held', flush=True)\n"
        "sys.stdin.read()\n"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", script, str(lock)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        yield holder.pid
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(timeout=30)


# --- what the console shows ---------------------------------------------------------------------------------


def desktop_png(path: Path) -> Path:
    """A capture with something drawn on it: a desktop bar, a window with the arm in it (where xwininfo's
    stand-in puts the viewer's window), a gradient, as a desktop would look."""
    from PIL import Image, ImageDraw

    image = Image.new("RGB", (1280, 720), (48, 10, 36))
    draw = ImageDraw.Draw(image)
    for x in range(0, 1280, 4):
        draw.line([(x, 40), (x, 720)], fill=(48 + x // 20, 10 + x // 40, 36))
    draw.rectangle([0, 0, 1280, 32], fill=(30, 30, 30))
    draw.rectangle([200, 120, 1080, 620], fill=(90, 110, 140), outline=(230, 230, 230))
    draw.ellipse([560, 280, 720, 440], fill=(240, 160, 40))
    image.save(path)
    return path


def black_viewer_png(path: Path) -> Path:
    """A desktop drawn around a black viewer window (MuJoCo drawing nothing): the window xwininfo's stand-in
    places at 1320x750+300+180 on a 1920x1080 screen, scaled as the capture is (to 1280x720)."""
    from PIL import Image, ImageDraw

    desktop_png(path)
    with Image.open(path) as opened:
        image = opened.convert("RGB")
    ImageDraw.Draw(image).rectangle([200, 120, 1079, 619], fill=(0, 0, 0))
    image.save(path)
    return path


def uniform_png(path: Path, colour: tuple[int, int, int] = (0, 0, 0)) -> Path:
    from PIL import Image

    Image.new("RGB", (1280, 720), colour).save(path)
    return path


# --- the host -----------------------------------------------------------------------------------------------


class HostSim:
    """One stand-in host: ROOT (the file system the scripts write), SIM (stand-in state), BIN (stand-ins).

    gpu_driver: nvidia-smi is there. xorg_module: the driver's Xorg module is installed (the DLAMI's case).
    """

    def __init__(
        self,
        base: Path,
        *,
        parameter: str = "",
        user_data: str = "",
        s3: dict[str, Path] | None = None,
        cdn: Path | None = None,
        gpu_driver: bool = True,
        xorg_module: bool = True,
    ) -> None:
        self.root = base / "root"
        self.sim = base / "sim"
        self.bin = self.sim / "bin"
        for directory in (
            self.root,
            self.sim,
            self.bin,
            self.sim / "agent",
            self.sim / "s3",
            self.sim / "fail",
            self.sim / "dpkg",
            self.sim / "users",
            self.sim / "groups",
            self.sim / "services",
            self.sim / "state",
        ):
            directory.mkdir(parents=True, exist_ok=True)
        for name, body in STANDINS.items():
            if name == "nvidia-smi" and not gpu_driver:
                continue
            path = self.bin / name
            path.write_text(_COMMON + textwrap.dedent(body))
            path.chmod(0o755)
        (self.sim / "parameter").write_text(parameter)
        (self.sim / "user-data.sh").write_text(user_data)
        (self.sim / "agent" / "healthz.json").write_text(json.dumps(HEALTHZ))
        (self.sim / "agent" / "state.json").write_text(json.dumps(STATE))
        desktop_png(self.sim / "screen.png")
        if cdn is not None:
            shutil.copytree(cdn, self.sim / "cdn")
        for key, source in (s3 or {}).items():
            target = self.sim / "s3" / key
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(source, target)
        # The Ubuntu cloud image's default user: an administrator, which the boot undoes.
        (self.sim / "users" / "ubuntu").touch()
        (self.sim / "groups" / "ubuntu").write_text("ubuntu\nadm\nsudo\nlxd\n")
        # Automatic updates as a fresh Ubuntu has them: the timers and the shutdown helper running.
        for unit in ("apt-daily.timer", "apt-daily-upgrade.timer", "unattended-upgrades"):
            (self.sim / "services" / unit).touch()
        (self.root / "etc" / "sudoers.d").mkdir(parents=True, exist_ok=True)
        (self.root / "etc" / "sudoers.d" / "90-cloud-init-users").write_text(
            "# Created by cloud-init\n\n# User rules for ubuntu\nubuntu ALL=(ALL) NOPASSWD:ALL\n"
        )
        (self.root / "etc" / "os-release").write_text('NAME="Ubuntu"\nVERSION_ID="24.04"\n')
        (self.root / "home" / "ubuntu").mkdir(parents=True, exist_ok=True)
        (self.root / "var" / "lib" / "cloud" / "data").mkdir(parents=True, exist_ok=True)
        (self.root / "var" / "lib" / "cloud" / "data" / "instance-id").write_text(INSTANCE_ID + "\n")
        (self.root / "var" / "lib" / "dpkg").mkdir(parents=True, exist_ok=True)
        (self.root / "var" / "lib" / "dpkg" / "lock-frontend").touch()
        (self.root / "proc" / "sys" / "kernel" / "random").mkdir(parents=True, exist_ok=True)
        (self.root / "proc" / "sys" / "kernel" / "random" / "boot_id").write_text(BOOT_ID + "\n")
        # GDM's Xorg, the pid the pgrep stand-in gives while X runs, with the authority file a client of :0
        # needs on its command line.
        (self.root / "proc" / XORG_PID).mkdir(parents=True, exist_ok=True)
        (self.root / "proc" / XORG_PID / "cmdline").write_bytes(
            b"\0".join(arg.encode() for arg in XORG_ARGS) + b"\0"
        )
        pci = self.root / "sys" / "bus" / "pci" / "devices" / "0000:00:1e.0"
        pci.mkdir(parents=True, exist_ok=True)
        (pci / "vendor").write_text("0x10de\n")
        # The DLAMI's driver: packaged, with its Xorg module.
        (self.sim / "dpkg" / "libnvidia-gl-580-server").write_text("580.95.05-0ubuntu0.24.04.2\n")
        if xorg_module:
            module = self.root / "usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so"
            module.parent.mkdir(parents=True, exist_ok=True)
            module.touch()

    @classmethod
    def attach(cls, base: Path) -> HostSim:
        """The HostSim of a tree made earlier (a copy of a booted host)."""
        host = cls.__new__(cls)
        host.root, host.sim, host.bin = base / "root", base / "sim", base / "sim" / "bin"
        return host

    def env(self, **extra: str) -> dict[str, str]:
        return {
            "PATH": f"{self.bin}:{os.environ['PATH']}",
            "HOME": str(self.sim),
            "LANG": "C.UTF-8",
            "ROOT": str(self.root),
            "SIM": str(self.sim),
            "TMPDIR": str(self.sim),
            # The repo's interpreter stands in for the host's python3.12, with its packages (the agent's
            # dependencies and the build backend); pip never reaches an index, only the lock's wheels here.
            "PYTHON": sys.executable,
            "VENV_ARGS": "--system-site-packages",
            "PIP_ARGS": f"--no-index --find-links {self.sim / 'wheels'}",
            **extra,
        }

    def run(self, script: Path | str, *args: str, stdin: str | None = None, **env: str):
        return subprocess.run(
            ["bash", str(script), *args],
            env=self.env(**env),
            input=stdin,
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )

    def fail(self, tool: str) -> None:
        (self.sim / "fail" / tool).touch()

    def calls(self) -> list[str]:
        path = self.sim / "calls.log"
        return path.read_text().splitlines() if path.exists() else []

    def signals(self) -> list[str]:
        path = self.sim / "signals.log"
        return path.read_text().splitlines() if path.exists() else []

    def armed(self) -> list[str]:
        """The alarms whose actions the host turned on, in call order."""
        path = self.sim / "armed.log"
        return path.read_text().splitlines() if path.exists() else []

    def handle_posts(self) -> list[dict[str, Any]]:
        path = self.sim / "handle.log"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    def file(self, path: str) -> str:
        return (self.root / path.lstrip("/")).read_text()

    def active(self, unit: str) -> bool:
        return (self.sim / "services" / unit.removesuffix(".service")).exists()

    def masked(self, unit: str) -> bool:
        return (self.sim / "masked" / unit.removesuffix(".service")).exists()

    def groups(self, user: str) -> list[str]:
        return (self.sim / "groups" / user).read_text().split()


def zip_dir(source: Path, target: Path) -> Path:
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as zf:
        for file in sorted(source.rglob("*")):
            if file.is_file() and "__pycache__" not in file.parts:
                zf.write(file, file.relative_to(source).as_posix())
    return target


def resolve(value: Any, refs: dict[str, str]) -> Any:
    """Resolve the intrinsics CDK puts in UserData, parameters and association commands, as CloudFormation
    would for this stack (pseudo parameters, Refs of named resources, Fn::Join, Fn::Sub, Fn::Select)."""
    pseudo = {
        "AWS::Region": REGION,
        "AWS::AccountId": ACCOUNT,
        "AWS::Partition": "aws",
        "AWS::URLSuffix": "amazonaws.com",
        "AWS::StackName": STACK_NAME,
    }
    if isinstance(value, str):
        return value
    if isinstance(value, list):
        return [resolve(v, refs) for v in value]
    if isinstance(value, dict) and len(value) == 1:
        ((fn, arg),) = value.items()
        if fn == "Ref":
            return pseudo.get(arg) or refs[arg]
        if fn == "Fn::Join":
            return arg[0].join(resolve(part, refs) for part in arg[1])
        if fn == "Fn::Sub":
            text = arg
            for name, val in pseudo.items():
                text = text.replace("${" + name + "}", val)
            return text
        if fn == "Fn::Base64":
            return resolve(arg, refs)
    raise ValueError(f"cannot resolve {value!r}")


def tree_digest(root: Path) -> dict[str, str]:
    """Content, mode and mtime of every file under root: a re-run that rewrites anything shows up."""
    digest = {}
    for path in sorted(root.rglob("*")):
        if path.is_symlink():
            digest[str(path.relative_to(root))] = "link:" + os.readlink(path)
        elif path.is_file():
            st = path.stat()
            content = hashlib.sha256(path.read_bytes()).hexdigest()
            digest[str(path.relative_to(root))] = f"{content}:{st.st_mode:o}:{st.st_mtime_ns}"
    return digest
