#!/bin/sh
# Started without a configuration file, redis-server keeps its protected mode, which refuses
# every client but loopback while no password is set: inside the compose network the API and
# the workers are other hosts (the official image's entrypoint does the same). Its files go to
# /data, the volume.
set -eu
if [ "${1:-}" = redis-server ]; then
  shift
  exec redis-server --protected-mode no --dir /data "$@"
fi
exec "$@"
