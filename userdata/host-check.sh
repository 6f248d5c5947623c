#!/usr/bin/env bash
# Is the twin host working, as a person at the DCV desktop would find it? One place for the rules, used
# three ways:
#   - bootstrap.sh sources it: its display step puts the console session on X (ensure_console_session),
#     its verify step waits for every check (verify_host) before signalling SUCCESS;
#   - after every start of the host, so101-twin-start.service runs `host-check.sh --on-start`: the same
#     order and waits, a verdict in its log, in /var/lib/so101-twin/last-start and as a CloudWatch metric;
#   - `twin instance check` runs it on the host through SSM Run Command (`bash host-check.sh`) and reads one
#     line per check: NAME<TAB>OK|WARN|FAIL<TAB>detail (exit status 1 when any FAIL).
# Checks: x-on-gpu, dcv-session, agent, telemetry (WARN only: no arm may be publishing), calibration (WARN
# only: an arm whose raw positions are turned into angles without its own LeRobot calibration), viewer (the
# same process for 20 s), screen (a capture of the console that is not one flat colour, and whose viewer
# window is not one flat colour either), version.

CHECK_VENV="${VENV:-/opt/so101-twin/venv}"
# The agent's DEFAULT_AGENT_URL (agents/twin/service/config.py), which install-agent.sh configures.
AGENT_HTTP="${AGENT_HTTP:-http://127.0.0.1:8080}"
CHECK_STATE=/var/lib/so101-twin
# The last capture of the console, kept on the host (`twin instance check --screenshot FILE` fetches it).
SCREENSHOT="$CHECK_STATE/console.png"
LAST_START="$CHECK_STATE/last-start"
# The on-start run's log, shipped to CloudWatch (bootstrap.sh, step logs); its metric lines: lib.sh.
START_LOG=/var/log/so101-twin-start.log
# DCV's port for browsers, TCP and UDP: bootstrap.sh writes it into dcv.conf (web-port, quic-port) and opens
# it in an active ufw. The stack's security group opens the same (stacks/network.py, DCV_PORT).
DCV_PORT=8443
# A viewer counts once the same process has run this long: its supervisor restarts a crashing one within
# seconds, so "a process exists" proves nothing.
VIEWER_STABLE_S=20
# Polls for what starts asynchronously (tries x 5 s): X, the DCV session, the agent, the viewer, the screen.
WAIT_X_TRIES=60
WAIT_DCV_TRIES=36
WAIT_AGENT_TRIES=60
WAIT_VIEWER_TRIES=36
WAIT_SCREEN_TRIES=12
DETAIL=""
GL_DETAIL=""
XWIN_TREE=""
XWIN_ROOT=""
XWIN_DETAIL=""
XWIN_MAP=""

check_x_on_gpu() {
  local smi gpu
  if ! pgrep -x Xorg >/dev/null; then
    DETAIL="no Xorg process: GDM has not started X (see /var/log/Xorg.0.log and journalctl -u gdm3)"
    return 1
  fi
  if ! command -v nvidia-smi >/dev/null 2>&1; then
    DETAIL="Xorg runs, but nvidia-smi is missing: no NVIDIA driver, so X cannot be on the GPU"
    return 1
  fi
  if ! smi="$(nvidia-smi 2>&1)"; then
    DETAIL="nvidia-smi failed: ${smi:0:300}"
    return 1
  fi
  # nvidia-smi's process table lists every client of the GPU; X on the GPU shows up as Xorg (type G).
  if [[ $smi != *Xorg* ]]; then
    DETAIL="Xorg runs but not on the NVIDIA GPU (nvidia-smi lists no Xorg process; check /etc/X11/xorg.conf)"
    return 1
  fi
  gpu="$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>&1)" || gpu="the GPU"
  # Xorg on the GPU can still render OpenGL in software (Mesa's llvmpipe, when the NVIDIA GLX library is
  # not the one X loaded): the viewer would run, slowly, on the CPU.
  if ! check_gl_on_gpu; then
    DETAIL="Xorg runs on ${gpu//$'\n'/; }, but $GL_DETAIL"
    return 1
  fi
  DETAIL="Xorg runs on ${gpu//$'\n'/; }; $GL_DETAIL"
}

# The X server's authority file, the -auth argument of a running Xorg (GDM's, readable by root), as AWS's
# DCV guide finds it for its checks on :0.
x_authority() {
  local pid arg next
  for pid in $(pgrep -x Xorg || true); do
    [ -r "${ROOT}/proc/$pid/cmdline" ] || continue
    next=0
    while IFS= read -r -d '' arg; do
      if [ "$next" = 1 ]; then
        echo "$arg"
        return 0
      fi
      [ "$arg" != -auth ] || next=1
    done <"${ROOT}/proc/$pid/cmdline"
  done
  return 1
}

# What renders OpenGL on X's display :0 (AWS's DCV guide checks the same with glxinfo): NVIDIA's driver, or
# GL_DETAIL names what does instead. glxinfo comes with mesa-utils (bootstrap.sh, step packages). Only a
# renderer that is not NVIDIA's fails: a question X could not be asked (no glxinfo, no -auth file, a refused
# connection) passes with what went wrong in the detail, since nvidia-smi above already saw X on the GPU and
# a guess about a host's X authority must not fail every boot.
check_gl_on_gpu() {
  local auth out line vendor="" renderer=""
  if ! command -v glxinfo >/dev/null 2>&1; then
    GL_DETAIL="not asked what renders OpenGL: glxinfo is missing (mesa-utils, the boot's packages step)"
    return 0
  fi
  if ! auth="$(x_authority)"; then
    GL_DETAIL="not asked what renders OpenGL: no Xorg process gives an -auth file"
    return 0
  fi
  # The output is captured whole and read here: no reader that stops early in a pipe (pipefail).
  if ! out="$(DISPLAY=:0 XAUTHORITY="$auth" timeout 30 glxinfo -B 2>&1)"; then
    GL_DETAIL="not told what renders OpenGL: glxinfo on :0 failed: ${out:0:300}"
    return 0
  fi
  while IFS= read -r line; do
    case "$line" in
      "OpenGL vendor string: "*) vendor="${line#*: }" ;;
      "OpenGL renderer string: "*) renderer="${line#*: }" ;;
    esac
  done <<<"$out"
  if [[ $vendor != *NVIDIA* ]]; then
    GL_DETAIL="OpenGL on :0 is rendered by ${renderer:-an unknown renderer} (${vendor:-no vendor given}), not"
    GL_DETAIL+=" NVIDIA's driver: software rendering on the CPU (see /var/log/Xorg.0.log for the GLX module)"
    return 1
  fi
  GL_DETAIL="OpenGL on :0: ${renderer:-?} (${vendor})"
}

# The owner of DCV's console session from `dcv list-sessions --json` (a JSON array of sessions with id,
# owner and type), or a line saying what was found instead.
dcv_console_session() {
  local out verdict
  if ! out="$(dcv list-sessions --json 2>&1)"; then
    DETAIL="dcv list-sessions failed: ${out:0:300} (is dcvserver running? systemctl status dcvserver)"
    return 1
  fi
  verdict="$(DCV_SESSIONS="$out" python3 - "$DESKTOP_USER" <<'PY'
import json, os, sys

user = sys.argv[1]
try:
    sessions = json.loads(os.environ["DCV_SESSIONS"])
except ValueError:
    print(f"FAIL\tdcv list-sessions --json printed no JSON: {os.environ['DCV_SESSIONS'][:200]!r}")
    raise SystemExit(0)
if not isinstance(sessions, list):
    sessions = []
console = [s for s in sessions if isinstance(s, dict) and s.get("id") == "console"]
if not console:
    ids = ", ".join(str(s.get("id")) for s in sessions if isinstance(s, dict)) or "none"
    print(f"FAIL\tno console session (sessions: {ids})")
elif console[0].get("type", "console") != "console":
    print(f"FAIL\tthe session 'console' is a {console[0].get('type')} session, not a console session")
elif console[0].get("owner") != user:
    print(f"FAIL\ta console session exists but is owned by {console[0].get('owner')}, not {user}")
else:
    print(f"OK\tconsole session owned by {user}")
PY
)"
  DETAIL="${verdict#*$'\t'}"
  [ "${verdict%%$'\t'*}" = OK ]
}

# The console session (dcv_console_session), and DCV listening where a browser connects: TCP DCV_PORT (its
# web port) on an address other than loopback (nothing there and the session is out of reach however open
# the security group is), and UDP DCV_PORT for QUIC (only noted when missing: the browser then streams over
# TCP). Asked of `ss` (iproute2), which names the listening process: one outside DCV's unit (another server
# on the port) would be what a browser reaches instead of DCV. DCV_VERIFIED: what a pass verified, for
# verify_host's summary (without ss, not the port).
check_dcv_session() {
  local tcp="" udp="" session other
  dcv_console_session || return 1
  session="$DETAIL"
  if ! command -v ss >/dev/null 2>&1; then
    DETAIL="${session}; not asked whether DCV listens on ${DCV_PORT}: ss is missing (iproute2)"
    DCV_VERIFIED="DCV console session (not asked whether DCV listens on ${DCV_PORT}: no ss)"
    return 0
  fi
  # Listening sockets' lines (no header): STATE RECV-Q SEND-Q LOCAL:PORT PEER:PORT; captured whole.
  if ! tcp="$(ss -Hltnp 2>&1)" || ! udp="$(ss -Hlun 2>&1)"; then
    DETAIL="${session}; not told whether DCV listens on ${DCV_PORT}: ss failed: ${tcp:0:200}${udp:0:200}"
    DCV_VERIFIED="DCV console session (not told whether DCV listens on ${DCV_PORT}: ss failed)"
    return 0
  fi
  if ! _listens "$tcp"; then
    DETAIL="${session}, but nothing listens on TCP ${DCV_PORT} beyond loopback, DCV's web port: no browser"
    DETAIL+=" can connect (dcv.conf [connectivity] web-port; journalctl -u dcvserver, /var/log/dcv/server.log)"
    return 1
  fi
  if other="$(_foreign_listener "$tcp")"; then
    DETAIL="${session}, but TCP ${DCV_PORT} is held by ${other}, not by DCV's server (dcvserver.service): a"
    DETAIL+=" browser reaches it instead; stop it or move it to another port (ss -ltnp), then restart dcvserver"
    return 1
  fi
  DETAIL="${session}; DCV listens on TCP ${DCV_PORT}"
  DCV_VERIFIED="DCV console session listening on ${DCV_PORT}"
  if _listens "$udp"; then
    DETAIL+=" and UDP ${DCV_PORT} (QUIC)"
  else
    DETAIL+=", not on UDP ${DCV_PORT}: no QUIC, browsers stream over TCP (dcv.conf enable-quic-frontend)"
  fi
}

# Whether a listing of `ss -H` has a socket on :DCV_PORT at an address other than loopback (0.0.0.0, [::],
# *, or an interface's own address; a scope like %eth0 may follow it).
_listens() {
  local fields
  while read -r -a fields; do
    if _public_dcv_port "${fields[3]:-}"; then return 0; fi
  done <<<"$1"
  return 1
}

_public_dcv_port() {
  [[ $1 == *":${DCV_PORT}" ]] || return 1
  [[ $1 != 127.* && $1 != "[::1]"* && $1 != "[::ffff:127."* ]]
}

# Of the sockets on :DCV_PORT beyond loopback in a listing of `ss -Hltnp`, the first none of whose processes
# is in dcvserver.service's cgroup, printed as "NAME (pid N)"; fails when DCV holds each, or ss names no
# process (not judged then). By the unit, not the name: whichever of DCV's processes holds the socket.
_foreign_listener() {
  local fields users name pid ours cgroup
  while read -r -a fields; do
    _public_dcv_port "${fields[3]:-}" || continue
    users="${fields[*]:5}"
    ours=0 name="" pid=""
    while [[ $users =~ \(\"([^\"]*)\",pid=([0-9]+) ]]; do
      name="${BASH_REMATCH[1]}" pid="${BASH_REMATCH[2]}"
      # A process gone since ss answered (DCV restarting) cannot be judged: not counted against DCV.
      # Read whole in the shell (no grep -q, which may stop reading early under pipefail); a file that
      # cannot be read (the process gone since ss answered) reads as empty.
      cgroup="$({ cat "${ROOT}/proc/${pid}/cgroup"; } 2>/dev/null || true)"
      if [ -z "$cgroup" ] || [[ $'\n'$cgroup$'\n' == *"/dcvserver.service"$'\n'* ]]; then ours=1; fi
      users="${users#*pid="${pid}"}"
    done
    if [ -n "$pid" ] && [ "$ours" = 0 ]; then
      echo "${name} (pid ${pid})"
      return 0
    fi
  done <<<"$1"
  return 1
}

# Sets AGENT_RESULT, TELEMETRY_RESULT and CALIBRATION_RESULT to "STATUS<TAB>detail" from the agent's
# /healthz and /state.
agent_results() {
  local health state active status line last="" rest
  if ! systemctl is-active --quiet so101-twin-agent.service; then
    active="$(systemctl is-active so101-twin-agent.service 2>&1 || true)"
    status="$(systemctl show so101-twin-agent.service -p ExecMainStatus --value 2>/dev/null || true)"
    TELEMETRY_RESULT=$'WARN\tno agent, no telemetry'
    CALIBRATION_RESULT=$'WARN\tno agent, no calibration state'
    if [ "$status" = 2 ]; then
      # `twin run` exits 2 on a configuration error, which the unit does not restart on: its log names
      # the setting.
      while IFS= read -r line; do
        [[ $line == *"configuration error"* ]] && last="$line"
      done <<<"$(journalctl -u so101-twin-agent.service -n 50 -o cat --no-pager 2>/dev/null || true)"
      AGENT_RESULT=$'FAIL\tthe agent refused its configuration (exit status 2, not restarted): '"${last:-see journalctl -u so101-twin-agent}"
      return 0
    fi
    AGENT_RESULT=$'FAIL\tso101-twin-agent.service is '"${active:-not active}"' (journalctl -u so101-twin-agent)'
    return 0
  fi
  health="$(curl -s --max-time 5 "$AGENT_HTTP/healthz" 2>&1 || true)"
  state="$(curl -s --max-time 5 "$AGENT_HTTP/state" 2>&1 || true)"
  local parsed
  parsed="$(HEALTH="$health" STATE="$state" "${ROOT}${CHECK_VENV}/bin/python" - <<'PY'
import json
import os


def load(name):
    try:
        return json.loads(os.environ[name])
    except ValueError:
        return None


health, state = load("HEALTH"), load("STATE")
if not isinstance(health, dict) or not isinstance(state, dict):
    shown = (os.environ["HEALTH"] or "nothing")[:200].replace("\n", " ")
    print(f"FAIL\tthe agent's HTTP API does not answer with JSON (got {shown!r})")
    print("WARN\tno telemetry state")
    print("WARN\tno calibration state")
    raise SystemExit(0)
agent = state.get("agent", {})
broker = agent.get("broker", {})
subscribed = broker.get("subscribes", 0)  # SUBSCRIBE requests the broker acknowledged (/state)
problems = []
if not agent.get("running"):
    problems.append("service not running")
if not broker.get("connected"):
    problems.append(f"not connected to the broker ({broker.get('last_error') or 'no error recorded'})")
if not subscribed:
    problems.append("no subscription acknowledged (IAM may deny iot:Subscribe)")
# A filter IoT Core refused (SUBACK Not authorized) while others were granted: those arms are never heard.
refused = sorted({f for c in broker.get("connections", []) for f in c.get("refused", [])})
if refused:
    problems.append(f"IoT Core refuses the subscription to {', '.join(refused)} (the role must allow iot:Subscribe on it)")
filters = ", ".join(agent.get("topic_filters", [])) or "none"
if problems:
    print(f"FAIL\t{'; '.join(problems)}; filters {filters}")
else:
    print(f"OK\tconnected and subscribed to {filters}")
devices = state.get("devices", {})
lines, all_online = [], bool(devices)
for device, entry in sorted(devices.items()):
    health = entry.get("health") or {}
    status = health.get("status", "?")
    all_online = all_online and status == "ONLINE"
    age = health.get("age_s")
    rate = health.get("rate_hz") or 0.0
    seen = "never seen" if age is None else f"last message {age:.1f} s ago"
    lines.append(f"{device} {status} {rate:.1f} Hz, {seen}")
detail = "; ".join(lines) or "no device has sent telemetry yet"
print(f"{'OK' if all_online else 'WARN'}\t{detail}")
# Each arm's LeRobot calibration (docs/agent.md, "Calibration"): without one, raw positions become the
# nominal arm's angles.
missing = sorted(d for d, e in devices.items() if e.get("uncalibrated"))
refused = sorted(d for d, e in devices.items() if e.get("calibration_problem"))
own = sum(1 for e in devices.values() if e.get("calibration"))
if missing:
    verb = "has" if len(missing) == 1 else "have"
    print(f"WARN\t{', '.join(missing)} {verb} no calibration: the nominal SO-101's zero and range, not the arm's")
elif refused:
    print(f"WARN\tthe newest calibration file of {', '.join(refused)} was refused: {devices[refused[0]]['calibration_problem']}")
else:
    print(f"OK\tno arm lacks one it needs ({own} of {len(devices)} decode with a calibration)")
PY
)" || parsed=$'FAIL\tcould not read the agent state with the venv python\nWARN\tno telemetry state\nWARN\tno calibration state'
  AGENT_RESULT="${parsed%%$'\n'*}"
  rest="${parsed#*$'\n'}"
  TELEMETRY_RESULT="${rest%%$'\n'*}"
  CALIBRATION_RESULT="${rest#*$'\n'}"
}

check_agent() {
  agent_results
  DETAIL="${AGENT_RESULT#*$'\t'}"
  [ "${AGENT_RESULT%%$'\t'*}" = OK ]
}

# The viewer counts when one `twin view` process of the desktop user has been alive for VIEWER_STABLE_S.
check_viewer() {
  local pids pid age oldest=-1
  pids="$(pgrep -u "$DESKTOP_USER" -f "${CHECK_VENV}/bin/twin view" || true)"
  if [ -z "$pids" ]; then
    DETAIL="twin view is not running in ${DESKTOP_USER}'s session (GNOME autostart starts its supervisor at login)"
    return 1
  fi
  for pid in $pids; do
    age="$(ps -o etimes= -p "$pid" 2>/dev/null || true)"
    age="${age//[[:space:]]/}"
    if [[ $age =~ ^[0-9]+$ ]] && [ "$age" -gt "$oldest" ]; then oldest="$age"; fi
  done
  if [ "$oldest" -lt 0 ]; then
    DETAIL="twin view runs, but ps could not tell how long (pids: ${pids//$'\n'/ })"
    return 1
  fi
  if [ "$oldest" -ge "$VIEWER_STABLE_S" ]; then
    DETAIL="twin view runs in ${DESKTOP_USER}'s desktop session (the same process for ${oldest} s)"
    return 0
  fi
  DETAIL="twin view keeps restarting in ${DESKTOP_USER}'s session: its process is ${oldest} s old, and a viewer"
  DETAIL+=" counts once one process has run ${VIEWER_STABLE_S} s (its supervisor logs why: journalctl _UID=\$(id -u"
  DETAIL+=" ${DESKTOP_USER}) | grep twin-view)"
  return 1
}

# The windows on X's display :0, asked with xwininfo (x11-utils, the boot's packages step): XWIN_TREE holds
# the window tree, XWIN_ROOT the screen's size, XWIN_MAP each MuJoCo window's "ID<TAB>map state" (the tree
# lists windows whether shown or not: a minimised or withdrawn one is IsUnMapped or IsUnviewable); or
# XWIN_DETAIL says why X was not asked. As for glxinfo, a question X could not be asked is no failure: the
# capture is then judged as a whole only.
ask_x_windows() {
  local auth line id answer
  XWIN_TREE="" XWIN_ROOT="" XWIN_DETAIL="" XWIN_MAP=""
  if ! command -v xwininfo >/dev/null 2>&1; then
    XWIN_DETAIL="xwininfo is missing (x11-utils, the boot's packages step)"
  elif ! auth="$(x_authority)"; then
    XWIN_DETAIL="no Xorg process gives an -auth file"
  elif ! XWIN_TREE="$(DISPLAY=:0 XAUTHORITY="$auth" timeout 30 xwininfo -root -tree 2>&1)"; then
    XWIN_DETAIL="xwininfo on :0 failed: ${XWIN_TREE:0:300}"
    XWIN_TREE=""
  elif ! XWIN_ROOT="$(DISPLAY=:0 XAUTHORITY="$auth" timeout 30 xwininfo -root 2>&1)"; then
    XWIN_DETAIL="xwininfo on :0 failed: ${XWIN_ROOT:0:300}"
    XWIN_TREE="" XWIN_ROOT=""
  fi
  [ -n "$XWIN_ROOT" ] || return 0
  while IFS= read -r line; do
    [[ $line =~ ^[[:space:]]*(0x[0-9a-f]+)\ \"MuJoCo ]] || continue
    id="${BASH_REMATCH[1]}"
    # A window gone since the tree was asked, or any other refusal: its state is not known, not failed.
    answer="$(DISPLAY=:0 XAUTHORITY="$auth" timeout 30 xwininfo -id "$id" 2>/dev/null)" || continue
    if [[ $answer =~ Map\ State:\ ([A-Za-z]+) ]]; then XWIN_MAP+="${id}"$'\t'"${BASH_REMATCH[1]}"$'\n'; fi
  done <<<"$XWIN_TREE"
}

# What a person would see: a capture of the console session, which must not be one flat colour (a black
# or blank screen), nor may the viewer's window in it be (MuJoCo drawing nothing: a desktop around a black
# window passed before). Kept on the host for `twin instance check --screenshot`.
check_screen() {
  local out
  mkdir -p "${ROOT}${CHECK_STATE}"
  if ! out="$(dcv get-screenshot --max-width 1280 --max-height 720 --format PNG \
    --output "${ROOT}${SCREENSHOT}" console 2>&1)"; then
    DETAIL="dcv get-screenshot of the console session failed: ${out:0:300}"
    return 1
  fi
  chmod 0640 "${ROOT}${SCREENSHOT}"
  ask_x_windows
  if ! out="$(judge_capture "${ROOT}${SCREENSHOT}" 2>&1)"; then
    DETAIL="could not analyse the capture: ${out:0:300}"
    return 1
  fi
  DETAIL="${out#*$'\t'}"
  [ "${out%%$'\t'*}" = OK ]
}

# judge_capture PNG: "OK|FAIL<TAB>detail" for the capture, and for the viewer's window in it when X told
# where it is (ask_x_windows). X's answers go through files: a window tree can outgrow an environment
# variable's limit (128 KiB).
judge_capture() {
  local xwin status=0
  xwin="$(mktemp -d)"
  printf '%s' "$XWIN_TREE" >"$xwin/tree"
  printf '%s' "$XWIN_ROOT" >"$xwin/root"
  printf '%s' "$XWIN_DETAIL" >"$xwin/detail"
  printf '%s' "$XWIN_MAP" >"$xwin/map"
  "${ROOT}${CHECK_VENV}/bin/python" - "$1" "$SCREENSHOT" "$xwin" "$DESKTOP_USER" <<'PY' || status=$?
import re
import sys
from pathlib import Path

from PIL import Image, ImageStat

# A line of `xwininfo -root -tree`: id "name": ("instance" "class")  WxH+relX+relY  +absX+absY, where an
# offset left of or above the screen prints as +-N. MuJoCo's viewer names its window "MuJoCo : <model>".
WINDOW = re.compile(r'^\s*(0x[0-9a-f]+) "MuJoCo[^"]*":.*\s(\d+)x(\d+)\+-?\d+\+-?\d+\s+\+(-?\d+)\+(-?\d+)\s*$')


def judge(image):
    """(flat, what it shows): one colour over nearly all of it, or hardly any variation, is nothing drawn."""
    small = image.copy()
    small.thumbnail((320, 320))
    pixels = small.width * small.height
    colours = small.getcolors(maxcolors=pixels)
    count, top = max(colours)
    share = count / pixels
    flat = share >= 0.99 or max(ImageStat.Stat(small).stddev) < 2.0
    shown = f"#{top[0]:02x}{top[1]:02x}{top[2]:02x} over {share:.1%}" if flat else f"{len(colours)} colours"
    return flat, shown


def viewer_window(image, xwin):
    """(its cut of the capture or None, where it is or why it was not judged, whether that fails)."""
    tree, root = (xwin / "tree").read_text(), (xwin / "root").read_text()
    if not tree:
        return None, f"not asked where the viewer's window is: {(xwin / 'detail').read_text()}", False
    found = [m.groups() for m in map(WINDOW.match, tree.splitlines()) if m]
    size = re.search(r"Width: (\d+)\s+Height: (\d+)", root)
    if not found:
        # Whether twin view runs is the viewer line's to say (`twin instance check` runs both either way).
        return None, "no MuJoCo window is on X's display :0", True
    if size is None:
        return None, "not told the screen's size by xwininfo -root", False
    # A window whose map state X did not tell counts as shown: the capture then judges it.
    states = dict(line.split("\t") for line in (xwin / "map").read_text().splitlines())
    shown = [f for f in found if states.get(f[0], "IsViewable") == "IsViewable"]
    if not shown:
        told = ", ".join(sorted(set(states.values())))
        return None, f"twin view runs, but its MuJoCo window is not shown on :0 (X says {told}: minimised" \
            " or withdrawn; restore it in the DCV session)", True
    w, h, x, y = max((tuple(int(v) for v in f[1:]) for f in shown), key=lambda f: f[0] * f[1])
    screen_w, screen_h = int(size.group(1)), int(size.group(2))
    scale = image.width / screen_w  # dcv get-screenshot keeps the screen's proportions
    box = [round(v * scale) for v in (max(x, 0), max(y, 0), min(x + w, screen_w), min(y + h, screen_h))]
    where = f"{w}x{h} at {x:+d}{y:+d}"
    if box[2] - box[0] < 8 or box[3] - box[1] < 8:
        return None, f"the viewer's window ({where}) is not on the {screen_w}x{screen_h} screen", True
    return image.crop(box), where, False


png, kept, xwin, user = sys.argv[1], sys.argv[2], Path(sys.argv[3]), sys.argv[4]
with Image.open(png) as opened:
    image = opened.convert("RGB")
size = f"{image.width}x{image.height}"
flat, shown = judge(image)
window, where, fails = viewer_window(image, xwin)
drawn = judge(window) if window is not None else (False, "")
if flat:
    print(f"FAIL\tthe console shows one flat colour ({shown} of {size}): no desktop is drawn (capture kept in"
          f" {kept})")
elif fails:
    print(f"FAIL\t{where} (capture kept in {kept})")
elif drawn[0]:
    print(f"FAIL\tthe viewer's window ({where}) shows one flat colour ({drawn[1]}): MuJoCo draws nothing in"
          f" it (its log: journalctl _UID=$(id -u {user}) | grep twin-view; capture kept in {kept})")
else:
    seen = f"the viewer drawn in its window ({where})" if window is not None else where
    print(f"OK\tthe console shows a desktop ({size}, {shown}), {seen}; capture kept in {kept}")
PY
  rm -rf "$xwin"
  return "$status"
}

# Prints NAME<TAB>STATUS<TAB>DETAIL with the detail on one line.
report() {
  local detail="${3//$'\t'/ }"
  printf '%s\t%s\t%s\n' "$1" "$2" "${detail//$'\n'/; }"
}

# DCV creates the automatic console session when it starts, and only if X runs then: without one while X
# runs, DCV came first (after a reboot, or a restart of GDM), so restart it; create the session by hand
# only when that did not help.
ensure_console_session() {
  wait_for 6 5 "the DCV console session" dcv_console_session && return 0
  if check_x_on_gpu; then
    log "no console session while X runs ($DETAIL): restarting dcvserver so it attaches to X"
    systemctl restart dcvserver
  fi
  wait_for "$WAIT_DCV_TRIES" 5 "the DCV console session" dcv_console_session && return 0
  log "no automatic console session ($DETAIL); creating it"
  dcv create-session --type=console --owner "$DESKTOP_USER" console || true
  wait_for 12 5 "the DCV console session" dcv_console_session
}

# _verified NAME OK|FAIL: one line of verify_host's table from DETAIL (uses its VERIFY_LINES and failures).
_verified() {
  VERIFY_LINES+=("$(report "$1" "$2" "$DETAIL")")
  log "$1: $DETAIL"
  [ "$2" = OK ] || failures+=("$1: $DETAIL")
}

# verify_host: wait for every check in the order a person meets them. Sets VERIFY_LINES (the table) and
# VERIFY_SUMMARY (the failures, or what was verified); fails when any required check does.
verify_host() {
  local failures=()
  VERIFY_LINES=()
  if wait_for "$WAIT_X_TRIES" 5 "X on the GPU" check_x_on_gpu; then _verified x-on-gpu OK; else
    _verified x-on-gpu FAIL
  fi
  if wait_for "$WAIT_DCV_TRIES" 5 "the DCV console session" check_dcv_session; then _verified dcv-session OK; else
    _verified dcv-session FAIL
  fi
  if wait_for "$WAIT_AGENT_TRIES" 5 "the agent subscribed" check_agent; then _verified agent OK; else
    _verified agent FAIL
  fi
  VERIFY_LINES+=("$(report telemetry "${TELEMETRY_RESULT%%$'\t'*}" "${TELEMETRY_RESULT#*$'\t'}")")
  log "telemetry: ${TELEMETRY_RESULT#*$'\t'} (not required: no arm needs to be publishing)"
  VERIFY_LINES+=("$(report calibration "${CALIBRATION_RESULT%%$'\t'*}" "${CALIBRATION_RESULT#*$'\t'}")")
  if wait_for "$WAIT_VIEWER_TRIES" 5 "a stable viewer" check_viewer; then
    _verified viewer OK
    # Once the viewer is up, the console must show it (GNOME may take a moment to paint).
    if wait_for "$WAIT_SCREEN_TRIES" 5 "a drawn desktop" check_screen; then _verified screen OK; else
      _verified screen FAIL
    fi
  else
    _verified viewer FAIL
    DETAIL="not captured: no viewer ran ${VIEWER_STABLE_S} s"
    _verified screen FAIL
  fi
  if [ ${#failures[@]} -gt 0 ]; then
    VERIFY_SUMMARY="$(printf '%s; ' "${failures[@]}")"
    VERIFY_SUMMARY="${VERIFY_SUMMARY%; }"
    return 1
  fi
  VERIFY_SUMMARY="X on the GPU, ${DCV_VERIFIED}, agent subscribed, viewer stable, desktop and viewer drawn"
  VERIFY_SUMMARY+=" on screen"
}

host_check_main() {
  local failed=0 name version last
  load_env "$ROOT/etc/so101-twin/deployment.env"
  DESKTOP_USER="${DESKTOP_USER:-ubuntu}"
  for name in x_on_gpu dcv_session agent viewer screen; do
    if "check_$name"; then
      report "${name//_/-}" OK "$DETAIL"
    else
      report "${name//_/-}" FAIL "$DETAIL"
      failed=1
    fi
    if [ "$name" = agent ]; then
      report telemetry "${TELEMETRY_RESULT%%$'\t'*}" "${TELEMETRY_RESULT#*$'\t'}"
      report calibration "${CALIBRATION_RESULT%%$'\t'*}" "${CALIBRATION_RESULT#*$'\t'}"
    fi
  done
  version="$(cat "$ROOT/var/lib/so101-twin/deployed-version" 2>/dev/null || echo none)"
  last="$(cat "$ROOT/var/lib/so101-twin/last-run" 2>/dev/null || echo "no run recorded")"
  report version OK "${version} (last run: ${last})"
  return "$failed"
}

# The kernel's id of this boot: the verdict of the on-start checks names it, so `twin instance start` can
# tell this start's verdict from the previous one's.
boot_id() { cat "${ROOT}/proc/sys/kernel/random/boot_id" 2>/dev/null || echo unknown; }

# emit_metric FAILED: the verdict as metrics (lib.sh), which the stack's HostChecksFailed alarm watches.
emit_metric() {
  emit_host_metrics "$CHECK_VENV" HostChecksFailed="$1" HostStartsVerified="$((1 - $1))"
}

# After every start (so101-twin-start.service): the console session on X, every check waited for, one
# verdict. Not while a boot or an update runs: they verify the host themselves.
on_start_main() {
  local verdict status failed=0
  mkdir -p "${ROOT}${CHECK_STATE}" "$(dirname "${ROOT}${START_LOG}")"
  exec > >(tee -a "${ROOT}${START_LOG}") 2>&1
  exec 9>"${ROOT}${CHECK_STATE}/run.lock"
  flock 9
  load_env "$ROOT/etc/so101-twin/deployment.env"
  DESKTOP_USER="${DESKTOP_USER:-ubuntu}"
  log "start checks of boot $(boot_id), deployment ${DEPLOYMENT_VERSION:-unknown}"
  # A run that was killed while it held apt still left its record: give the timers back.
  restore_apt "${ROOT}${CHECK_STATE}" || log "could not restore the apt timers"
  # The host is in service again: a silent agent pages (the first boot turned this on already; a deploy that
  # changed the alarm may have turned it off). Not a check of its own: the verdict is about the desktop.
  arm_silent_alarm || true
  if wait_for "$WAIT_X_TRIES" 5 "X on the GPU" check_x_on_gpu; then
    ensure_console_session || log "dcv-session: $DETAIL"
  fi
  if verify_host; then status=PASS; else
    status=FAIL
    failed=1
  fi
  verdict="boot=$(boot_id) $(date -Is) $status $VERIFY_SUMMARY"
  printf '%s\n' "$verdict" "${VERIFY_LINES[@]}" >"${ROOT}${LAST_START}.new"
  mv -f "${ROOT}${LAST_START}.new" "${ROOT}${LAST_START}"
  emit_metric "$failed" || log "could not write the HostChecksFailed metric line"
  log "verdict: $status: $VERIFY_SUMMARY"
  return "$failed"
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  set -Eeuo pipefail
  HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
  LOG_TAG=host-check
  # shellcheck source=userdata/lib.sh
  . "$HERE/lib.sh"
  if [ "${1:-}" = --on-start ]; then
    on_start_main
  else
    host_check_main
  fi
fi
