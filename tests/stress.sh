#!/usr/bin/env bash
# make test-stress: the whole suite RUNS times in a row, each in a new random order (pytest-randomly) on one
# more xdist worker than cores, as `make test` runs it, with one busy process per core competing with it.
# A test that waits on a sleep, on one thread's timing or on another test's leftovers fails here long before
# it fails one CI run in ten. Extra arguments go to pytest.
set -Eeuo pipefail
cd "$(dirname "$0")/.."

runs="${1:-3}"
shift || true
cores="$(nproc)"
hogs=()

stop_hogs() {
  if [ "${#hogs[@]}" -gt 0 ]; then
    kill "${hogs[@]}" 2>/dev/null || true
    wait "${hogs[@]}" 2>/dev/null || true
  fi
}
trap stop_hogs EXIT

for _ in $(seq "$cores"); do
  # A pure CPU spinner at the suite's own priority: the scheduler shares each core between it and the tests.
  python3 -c 'while True: pass' &
  hogs+=("$!")
done
echo "test-stress: ${runs} runs in random order, ${cores} busy processes (one per core)"

for run in $(seq "$runs"); do
  seed="$(od -An -N4 -tu4 /dev/urandom | tr -d ' ')"
  echo "test-stress: run ${run}/${runs}, seed ${seed} (to reproduce: .venv/bin/pytest --randomly-seed=${seed})"
  started="$(date +%s)"
  if ! .venv/bin/pytest --randomly-seed="$seed" -n "$(( cores + 1 ))" -q "$@"; then
    echo "test-stress: run ${run} FAILED after $(( $(date +%s) - started )) s; seed ${seed}" >&2
    exit 1
  fi
  echo "test-stress: run ${run} passed in $(( $(date +%s) - started )) s"
done
echo "test-stress: ${runs} of ${runs} runs passed"
