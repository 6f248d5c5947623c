"""A stand-in twin host for running the real userdata/ scripts in a test: a temporary root plus stand-ins for
the system tools, first on PATH.

What is real: bash, the scripts themselves (the very text the stack renders into UserData and the State
Manager association), tar on a DCV tarball of realistic size and layout, python3 (venv, pip, zipfile, JSON),
coreutils, flock. What stands in, and why: the tools that would change this machine or need AWS, a GPU, a
display or a package mirror (apt-get, dpkg-query, dpkg, systemctl, nvidia-smi, nvidia-xconfig, dcv, gpg,
chpasswd, chown, usermod, id, glib-compile-schemas, pgrep, aws, curl, sleep). Each stand-in logs its
arguments to `calls.log` and keeps the host's state in SIM (installed packages, active services, whether X
runs on the GPU, the DCV sessions), and encodes the dependencies that matter for the order of the boot: X
starts on the GPU only with the NVIDIA Xorg module and an xorg.conf for the nvidia driver; dcvserver creates
the automatic console session only if X runs when it starts; the viewer runs once X runs and the autostart
entry and its supervisor exist; the agent answers /healthz only while its service is active.
A file SIM/fail/<tool> makes that stand-in fail (to test a failing step).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import random
import shutil
import subprocess
import tarfile
import textwrap
import zipfile
from pathlib import Path
from typing import Any

INSTANCE_ID = "i-0123456789abcdef0"
REGION = "us-east-1"
ACCOUNT = "111111111111"
STACK_NAME = "So101TwinStack"
HANDLE_URL = (
    "https://cloudformation-waitcondition-us-east-1.s3.amazonaws.com/arn%3Aaws%3Acloudformation/handle?sig=x"
)
SECRET_ARN = f"arn:aws:secretsmanager:{REGION}:{ACCOUNT}:secret:HostDcvPassword-AbCdEf"
LOG_GROUP = f"/so101-twin/{STACK_NAME}/host"
HISTORY_BUCKET = "so101twinstack-historybucket-0123456789ab"
DCV_VERSION = "2025.0-20103"
DCV_DIR = f"nice-dcv-{DCV_VERSION}-ubuntu2404-x86_64"
DCV_PACKAGES = {  # member -> size in bytes: several MB in all, like the real tarball's debs
    f"nice-dcv-server_{DCV_VERSION.replace('-', '.')}-1_amd64.ubuntu2404.deb": 3_000_000,
    f"nice-dcv-web-viewer_{DCV_VERSION.replace('-', '.')}-1_amd64.ubuntu2404.deb": 2_000_000,
    "nice-xdcv_2025.0.655-1_amd64.ubuntu2404.deb": 1_000_000,
    "nice-dcv-gl_2025.0.1158-1_amd64.ubuntu2404.deb": 1_000_000,
    "nice-dcv-gltest_2025.0.346-1_amd64.ubuntu2404.deb": 500_000,
}

_COMMON = r"""#!/usr/bin/env bash
# Stand-in for a system tool (tests/infra/hostsim.py).
set -u
me="$(basename "$0")"
printf '%s\n' "$me $*" >>"$SIM/calls.log"
if [ -e "$SIM/fail/$me" ]; then echo "$me: failing on purpose (test)" >&2; exit 1; fi
mark() { mkdir -p "$SIM/$1"; : >"$SIM/$1/$2"; }
has() { [ -e "$SIM/$1/$2" ]; }
"""

STANDINS: dict[str, str] = {
    "apt-get": r"""
while [ "${1:-}" = -o ]; do shift 2; done  # -o Option=value
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
      mark dpkg "$pkg"
      case "$pkg" in
        amazon-cloudwatch-agent)
          mkdir -p "$ROOT/opt/aws/amazon-cloudwatch-agent/bin"
          cp "$SIM/bin/amazon-cloudwatch-agent-ctl" "$ROOT/opt/aws/amazon-cloudwatch-agent/bin/" ;;
        xserver-xorg-video-nvidia-*)
          mkdir -p "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg"
          : >"$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ;;
        nice-dcv-server) mark users dcv; mkdir -p "$ROOT/etc/dcv" ;;
        gdm3) mkdir -p "$ROOT/etc/gdm3" ;;
      esac
    done ;;
  *) echo "apt-get stand-in: unsupported $*" >&2; exit 100 ;;
esac
""",
    "dpkg-query": r"""
# dpkg-query -W -f=FORMAT PATTERN
format="${2#-f=}"; pattern="$3"
if [ "$format" = '${Status}' ]; then
  if has dpkg "$pattern"; then printf 'install ok installed'; exit 0; fi
  echo "dpkg-query: no packages found matching $pattern" >&2; exit 1
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
args=("$@"); quiet=0
[ "${args[0]}" = --global ] && args=("${args[@]:1}")
[ "${args[1]:-}" = --quiet ] && { quiet=1; args=("${args[0]}" "${args[@]:2}"); }
unit="${args[1]:-}"; unit="${unit%.service}"
x_can_start() {
  [ -e "$ROOT/usr/lib/x86_64-linux-gnu/nvidia/xorg/nvidia_drv.so" ] &&
    grep -qs 'Driver.*"nvidia"' "$ROOT/etc/X11/xorg.conf" &&
    grep -qs AllowEmptyInitialConfiguration "$ROOT/etc/X11/xorg.conf"
}
case "${args[0]}" in
  daemon-reload|enable) ;;
  get-default) cat "$SIM/default.target" 2>/dev/null || echo multi-user.target ;;
  set-default) echo "$unit" >"$SIM/default.target" ;;
  is-active)
    if has services "$unit"; then [ "$quiet" = 1 ] || echo active; exit 0; fi
    [ "$quiet" = 1 ] || echo inactive; exit 3 ;;
  restart|start)
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
        if has state xorg && grep -qs '^create-session = true' "$ROOT/etc/dcv/dcv.conf"; then
          sed -n 's/^owner = "\(.*\)"/\1/p' "$ROOT/etc/dcv/dcv.conf" >"$SIM/state/console"
        fi ;;
    esac ;;
  *) echo "systemctl stand-in: unsupported ${args[*]}" >&2; exit 1 ;;
esac
""",
    "pgrep": r"""
# pgrep -x Xorg | pgrep -u USER -f PATTERN
if [ "$1" = -x ] && [ "$2" = Xorg ]; then has state xorg && { echo 1234; exit 0; }; exit 1; fi
if [ "$1" = -u ]; then has state viewer && { echo 2345; exit 0; }; exit 1; fi
exit 1
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
    if has state console; then echo "Session: 'console' (owner:$(cat "$SIM/state/console") type:console)"
    else echo "There are no sessions available."; fi ;;
  create-session)
    has state xorg || { echo "Could not create session: no X server" >&2; exit 1; }
    owner=""; for a in "$@"; do case "$a" in --owner) ;; esac; done
    while [ $# -gt 0 ]; do [ "$1" = --owner ] && owner="$2"; shift; done
    echo "$owner" >"$SIM/state/console" ;;
esac
""",
    "gpg": r"""exit 0""",
    "glib-compile-schemas": r"""exit 0""",
    "usermod": r"""exit 0""",
    "chown": r"""exit 0""",
    "sleep": r"""exit 0""",
    "chpasswd": r"""
IFS= read -r line
user="${line%%:*}"; password="${line#*:}"
printf 'chpasswd user=%s length=%s\n' "$user" "${#password}" >>"$SIM/chpasswd.log"
""",
    "id": r"""
case "$1" in
  -u) has users "$2" && { echo 1000; exit 0; }; echo "id: '$2': no such user" >&2; exit 1 ;;
  -nG) has users "$2" || { echo "id: '$2': no such user" >&2; exit 1; }; echo "$2" ;;
esac
""",
    "aws": r"""
case "$1 $2" in
  "ssm get-parameter") cat "$SIM/parameter" ;;
  "s3 cp")
    for a in "$@"; do case "$a" in s3://*) src="${a#s3://}" ;; esac; done
    dst="${!#}"
    if [ ! -f "$SIM/s3/$src" ]; then
      echo "fatal error: An error occurred (404) when calling the HeadObject operation:" \
        "Key \"$src\" does not exist" >&2
      exit 1
    fi
    cp "$SIM/s3/$src" "$dst" ;;
  "secretsmanager describe-secret") echo "v-1" ;;
  "secretsmanager get-secret-value") echo "Gener4tedPassw0rdOfTwentyFour" ;;
  "cloudformation signal-resource") printf '%s\n' "$*" >>"$SIM/signals.log" ;;
  *) echo "aws stand-in: unsupported $*" >&2; exit 2 ;;
esac
""",
    "curl": r"""
out=""; method=GET; data=""; url=""
while [ $# -gt 0 ]; do
  case "$1" in
    -o) out="$2"; shift ;;
    -X) method="$2"; shift ;;
    -H|--max-time) shift ;;
    --data-binary) data="$2"; shift ;;
    -*) ;;
    *) url="$1" ;;
  esac
  shift
done
[ "$data" = @- ] && data="$(cat)"
emit() { if [ -n "$out" ]; then cat >"$out"; else cat; fi; }
case "$url" in
  */NICE-GPG-KEY) echo "-----BEGIN PGP PUBLIC KEY BLOCK-----" | emit ;;
  */nice-dcv-ubuntu2404-x86_64.tgz) emit <"$SIM/dcv.tgz" ;;
  *amazon-cloudwatch-agent.deb) echo "Package: amazon-cloudwatch-agent" | emit ;;
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
    "devices": {"arm-001": {"device_id": "arm-001", "status": "OFFLINE", "age_s": None, "rate_hz": 0.0}},
}


def make_dcv_tarball(path: Path, seed: int = 101) -> Path:
    """A tarball laid out like AWS's (one versioned directory of .deb files), incompressible, several MB."""
    rng = random.Random(seed)
    with tarfile.open(path, "w:gz") as tar:
        for name, size in DCV_PACKAGES.items():
            data = rng.randbytes(size)
            info = tarfile.TarInfo(f"{DCV_DIR}/{name}")
            info.size = size
            tar.addfile(info, io.BytesIO(data))
        notes = b"DCV release notes (stand-in)\n"
        info = tarfile.TarInfo(f"{DCV_DIR}/README")
        info.size = len(notes)
        tar.addfile(info, io.BytesIO(notes))
    return path


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


class HostSim:
    """One stand-in host: ROOT (the file system the scripts write), SIM (stand-in state), BIN (stand-ins)."""

    def __init__(
        self,
        base: Path,
        *,
        parameter: str = "",
        user_data: str = "",
        s3: dict[str, Path] | None = None,
        dcv_tgz: Path | None = None,
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
        ):
            directory.mkdir(parents=True, exist_ok=True)
        for name, body in STANDINS.items():
            path = self.bin / name
            path.write_text(_COMMON + textwrap.dedent(body))
            path.chmod(0o755)
        (self.sim / "parameter").write_text(parameter)
        (self.sim / "user-data.sh").write_text(user_data)
        (self.sim / "agent" / "healthz.json").write_text(json.dumps(HEALTHZ))
        (self.sim / "agent" / "state.json").write_text(json.dumps(STATE))
        if dcv_tgz is not None:
            shutil.copy(dcv_tgz, self.sim / "dcv.tgz")
        for key, source in (s3 or {}).items():
            target = self.sim / "s3" / key
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(source, target)
        (self.sim / "dpkg").mkdir(exist_ok=True)
        (self.sim / "users").mkdir(exist_ok=True)
        (self.sim / "users" / "ubuntu").touch()
        (self.root / "etc").mkdir(exist_ok=True)
        (self.root / "etc" / "os-release").write_text('NAME="Ubuntu"\nVERSION_ID="24.04"\n')
        (self.root / "home" / "ubuntu").mkdir(parents=True, exist_ok=True)
        (self.root / "var" / "lib" / "cloud" / "data").mkdir(parents=True, exist_ok=True)
        (self.root / "var" / "lib" / "cloud" / "data" / "instance-id").write_text(INSTANCE_ID + "\n")

    def env(self, **extra: str) -> dict[str, str]:
        import sys

        return {
            "PATH": f"{self.bin}:{os.environ['PATH']}",
            "HOME": str(self.sim),
            "LANG": "C.UTF-8",
            "ROOT": str(self.root),
            "SIM": str(self.sim),
            "TMPDIR": str(self.sim),
            # The repo's interpreter stands in for the host's python3.12; --no-deps keeps pip offline-safe
            # (the runtime wheels are tested elsewhere; here what matters is what the scripts do).
            "PYTHON": sys.executable,
            "VENV_ARGS": "--system-site-packages",
            "PIP_ARGS": "--no-deps",
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

    def handle_posts(self) -> list[dict[str, Any]]:
        path = self.sim / "handle.log"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    def file(self, path: str) -> str:
        return (self.root / path.lstrip("/")).read_text()


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
