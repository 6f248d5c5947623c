#!/usr/bin/env bash
# Is the twin host working? One place for the rules, used twice:
#   - bootstrap.sh sources it and its verify step waits for the required checks before signalling SUCCESS;
#   - `twin instance check` runs it on the host through SSM Run Command:
#       bash /opt/so101-twin/userdata/host-check.sh
#     and reads one line per check: NAME<TAB>OK|WARN|FAIL<TAB>detail (exit status 1 when any FAIL).
# Checks: x-on-gpu, dcv-session, agent, telemetry (WARN only: no arm may be publishing), viewer, version.

CHECK_VENV="${VENV:-/opt/so101-twin/venv}"
# The agent's DEFAULT_AGENT_URL (agents/twin/service/config.py), which install-agent.sh configures.
AGENT_HTTP="${AGENT_HTTP:-http://127.0.0.1:8080}"
DETAIL=""

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
  DETAIL="Xorg runs on ${gpu//$'\n'/; }"
}

check_dcv_session() {
  local out
  if ! out="$(dcv list-sessions 2>&1)"; then
    DETAIL="dcv list-sessions failed: ${out:0:300} (is dcvserver running? systemctl status dcvserver)"
    return 1
  fi
  if [[ $out == *"Session: 'console' (owner:${DESKTOP_USER} "* ]]; then
    DETAIL="console session owned by ${DESKTOP_USER}"
    return 0
  fi
  if [[ $out == *"Session: 'console'"* ]]; then
    DETAIL="a console session exists but is not owned by ${DESKTOP_USER}: ${out//$'\n'/; }"
  else
    DETAIL="no console session (dcv list-sessions: ${out:-nothing})"
  fi
  return 1
}

# Sets AGENT_RESULT and TELEMETRY_RESULT to "STATUS<TAB>detail" from the agent's /healthz and /state.
agent_results() {
  local health state active
  if ! systemctl is-active --quiet so101-twin-agent.service; then
    active="$(systemctl is-active so101-twin-agent.service 2>&1 || true)"
    AGENT_RESULT=$'FAIL\tso101-twin-agent.service is '"${active:-not active}"' (journalctl -u so101-twin-agent)'
    TELEMETRY_RESULT=$'WARN\tno agent, no telemetry'
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
    raise SystemExit(0)
agent = state.get("agent", {})
broker = agent.get("broker", {})
subscribed = broker.get("subscribed", broker.get("subscribes", 0))
problems = []
if not agent.get("running"):
    problems.append("service not running")
if not broker.get("connected"):
    problems.append(f"not connected to the broker ({broker.get('last_error') or 'no error recorded'})")
if not subscribed:
    problems.append("no subscription acknowledged (IAM may deny iot:Subscribe)")
filters = ", ".join(agent.get("topic_filters", [])) or "none"
if problems:
    print(f"FAIL\t{'; '.join(problems)}; filters {filters}")
else:
    print(f"OK\tconnected and subscribed to {filters}")
devices = state.get("devices", {})
lines, all_online = [], bool(devices)
for device, entry in sorted(devices.items()):
    status = entry.get("status", "?")
    all_online = all_online and status == "ONLINE"
    age = entry.get("age_s")
    rate = entry.get("rate_hz") or 0.0
    seen = "never seen" if age is None else f"last message {age:.1f} s ago"
    lines.append(f"{device} {status} {rate:.1f} Hz, {seen}")
detail = "; ".join(lines) or "no device has sent telemetry yet"
print(f"{'OK' if all_online else 'WARN'}\t{detail}")
PY
)" || parsed=$'FAIL\tcould not read the agent state with the venv python\nWARN\tno telemetry state'
  AGENT_RESULT="${parsed%%$'\n'*}"
  TELEMETRY_RESULT="${parsed#*$'\n'}"
}

check_agent() {
  agent_results
  DETAIL="${AGENT_RESULT#*$'\t'}"
  [ "${AGENT_RESULT%%$'\t'*}" = OK ]
}

check_viewer() {
  if pgrep -u "$DESKTOP_USER" -f "${CHECK_VENV}/bin/twin view" >/dev/null; then
    DETAIL="twin view runs in ${DESKTOP_USER}'s desktop session"
    return 0
  fi
  DETAIL="twin view is not running in ${DESKTOP_USER}'s session (GNOME autostart starts its supervisor at login)"
  return 1
}

# Prints NAME<TAB>STATUS<TAB>DETAIL with the detail on one line.
report() {
  local detail="${3//$'\t'/ }"
  printf '%s\t%s\t%s\n' "$1" "$2" "${detail//$'\n'/; }"
}

host_check_main() {
  local failed=0 name version last
  load_env "$ROOT/etc/so101-twin/deployment.env"
  DESKTOP_USER="${DESKTOP_USER:-ubuntu}"
  for name in x_on_gpu dcv_session agent viewer; do
    if "check_$name"; then
      report "${name//_/-}" OK "$DETAIL"
    else
      report "${name//_/-}" FAIL "$DETAIL"
      failed=1
    fi
    if [ "$name" = agent ]; then
      report telemetry "${TELEMETRY_RESULT%%$'\t'*}" "${TELEMETRY_RESULT#*$'\t'}"
    fi
  done
  version="$(cat "$ROOT/var/lib/so101-twin/deployed-version" 2>/dev/null || echo none)"
  last="$(cat "$ROOT/var/lib/so101-twin/last-run" 2>/dev/null || echo "no run recorded")"
  report version OK "${version} (last run: ${last})"
  return "$failed"
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  set -Eeuo pipefail
  HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
  # shellcheck source=userdata/lib.sh
  . "$HERE/lib.sh"
  host_check_main
fi
