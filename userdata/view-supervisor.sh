#!/usr/bin/env bash
# Keeps `twin view` running in the desktop session (installed as /opt/so101-twin/bin/twin-view-supervised
# and started by the GNOME autostart entry, which by itself would start the viewer once and never again).
# Restarts the viewer when it exits (backing off up to 30 s while it keeps failing) and when a deploy
# replaced the agent package (the venv's source stamp changed), so the window always runs current code.
# It only ever signals the one viewer process it started.
#   ROOT           prefix for the venv (tests); VIEW_POLL_S seconds between looks (default 5)
#   VIEW_MAX_STARTS stop after this many starts (tests; default: never)
set -Eeuo pipefail

ROOT="${ROOT:-}"
VENV="${ROOT}/opt/so101-twin/venv"
STAMP="$VENV/.so101-twin-source.sha256"
POLL_S="${VIEW_POLL_S:-5}"
MAX_STARTS="${VIEW_MAX_STARTS:-0}"

log() { echo "twin-view-supervised: $(date -Is) $*" >&2; }
stamp() { cat "$STAMP" 2>/dev/null || echo none; }

starts=0
backoff=1
child=""
# Every background job, not only "$child": a TERM that lands between the viewer's fork and `child=$!` finds
# child empty, and the viewer would outlive its supervisor (a stress run's test saw its stderr held open).
trap 'kill $(jobs -p) 2>/dev/null || true; exit 0' TERM INT HUP
while :; do
  started_with="$(stamp)"
  "$VENV/bin/twin" view &
  child=$!
  starts=$((starts + 1))
  began=$SECONDS
  log "started twin view (pid $child, start $starts)"
  while kill -0 "$child" 2>/dev/null; do
    sleep "$POLL_S"
    if [ "$(stamp)" != "$started_with" ]; then
      log "the agent package changed; restarting the viewer"
      kill "$child" 2>/dev/null || true
      backoff=0
      break
    fi
  done
  rc=0
  wait "$child" || rc=$?
  child=""
  log "twin view exited with status $rc"
  if [ "$MAX_STARTS" -gt 0 ] && [ "$starts" -ge "$MAX_STARTS" ]; then
    exit 0
  fi
  # A viewer that ran for a while gets restarted at once; one that keeps dying waits longer each time.
  if [ $((SECONDS - began)) -gt 60 ]; then backoff=1; fi
  sleep "$backoff"
  backoff=$((backoff * 2 > 30 ? 30 : (backoff == 0 ? 1 : backoff * 2)))
done
