#!/usr/bin/env bash
# A lent GPU's work, prepared here and run there in one call (docs/benchmarks.md, "Still to
# measure"; the device tool's notes: 15 device minutes a session, 10 a call, 64 MiB carried, at
# most 8 files back from $OUT).
#
#   here:   bash benchmarks/lend.sh prepare panoptic|fox
#           wheels the device image lacks into .whl/ (the versions of this .venv), the data
#           into .lend/ (the Panoptic pack of FRAMES, default 0:50; or the fox and its
#           triangulated seeds at 1/4), both ignored by git through .git/info/exclude
#   there:  bash benchmarks/lend.sh run TASK [ARGS...]    (carry .whl and .lend)
#           installs the wheels into /tmp/site, builds our extension (and gsplat's for the fox
#           tasks), runs TASK, and packs what it wrote (JSON, logs, text, pictures; no PLYs or
#           checkpoints) into $OUT/r.tgz every 15 s, so a call cut short still returns it.
#           panoptic ARGS: passed to benchmarks/panoptic.py after the pack and --out
#             (e.g. --frames 0:10 --gop 10 --mesh-voxels 256);
#           fox-seeds SYSTEM...: keyframe_gpu.py at 1/4, 7,500 steps, seeds 0 1 2 in turn;
#           fox-full SYSTEM...: keyframe_gpu.py at full resolution, 3,000 steps, seed 0.
set -uo pipefail
cd "$(dirname "$0")/.."
verb=${1:-}; task=${2:-}; shift 2 2>/dev/null || { echo "usage: $0 prepare|run TASK" >&2; exit 2; }

# Imported by the code each task runs and missing from the device image (KINDS.md's list).
CORE="pydantic pydantic-core annotated-types typing-inspection typing-extensions plyfile openexr
      trimesh"
SERVICE="fastapi starlette uvicorn sqlalchemy pydantic-settings python-dotenv celery kombu billiard
         vine amqp click-didyoumean click-plugins click-repl prompt-toolkit wcwidth tzlocal"

prepare() {
  for p in /.whl/ /.lend/; do grep -qx "$p" .git/info/exclude 2>/dev/null \
    || echo "$p" >> .git/info/exclude; done
  mkdir -p .whl .lend
  local names="$CORE" pins=() frozen
  [ "$task" = panoptic ] && names="$names $SERVICE"
  frozen=$(.venv/bin/python -m pip freeze 2>/dev/null | tr 'A-Z_' 'a-z-')
  for n in $names; do pins+=("$(grep -m1 "^$n==" <<<"$frozen" || echo "$n")"); done
  [ "$task" = fox ] && pins+=("gsplat==1.5.3")
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d .whl "${pins[@]}" || return 1
  case $task in
    panoptic) rm -rf .lend/panoptic
              .venv/bin/python benchmarks/panoptic.py --out .lend/panoptic --pack \
                --frames "${FRAMES:-0:50}" ;;
    fox) [ -d .lend/fox ] || cp -r ../shared/data/fox .lend/fox
         .venv/bin/python benchmarks/keyframe_gpu.py .lend/fox --out /tmp/lend-seeds \
           --downscale 4 --steps 3 --systems ours-3dgs --profile-steps 0 --mesh-voxels 0 \
           --device cpu --seed-file .lend/seeds4.npz > /dev/null ;;
    *) echo "prepare: panoptic or fox" >&2; return 2 ;;
  esac
  du -sh .whl .lend
}

snap() {  # what the task wrote so far, small files only, into $OUT/r.tgz
  (cd /tmp && find r -type f \( -name '*.json' -o -name '*.log' -o -name '*.txt' -o -name '*.md' \
     -o -name '*.png' -o -name '*.jpg' \) -size -8M -print0 \
     | tar czf "$OUT/r.tgz.tmp" --null -T - && mv "$OUT/r.tgz.tmp" "$OUT/r.tgz")
}

run() {
  export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site OMP_NUM_THREADS=4
  mkdir -p /tmp/r
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || return 3
  # imageio_ffmpeg (its wheel is 30 MB: the relit MP4s) is imported by core.relight; the
  # tasks here write no video (no HDRI travels), so an empty module stands in for it.
  python3 -c "import imageio_ffmpeg" 2>/dev/null || { mkdir -p /tmp/site/imageio_ffmpeg \
    && touch /tmp/site/imageio_ffmpeg/__init__.py; }
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > /tmp/r/gpu.txt
  local t0=$SECONDS gs=--no-gsplat
  [ "$task" != panoptic ] && gs=
  python3 benchmarks/gpu.py --build-only $gs > /tmp/r/build.log 2>&1
  echo "builds: rc $? in $((SECONDS - t0)) s"; snap
  # The snapshots in the background: TERM ends the loop at once in its sleep and only after a
  # snapshot under way, so the last one below never writes r.tgz.tmp beside another.
  ( trap exit TERM; while true; do sleep 15 & wait $!; snap; done ) & local snapper=$!
  case $task in
    panoptic) python3 benchmarks/panoptic.py .lend/panoptic --out /tmp/r/p "$@" \
                > /tmp/r/panoptic.log 2>&1; tail -30 /tmp/r/panoptic.log ;;
    fox-seeds) for s in 0 1 2; do
                 python3 benchmarks/keyframe_gpu.py .lend/fox --out /tmp/r/s$s --downscale 4 \
                   --steps 7500 --seed $s --systems "$@" --profile-steps 0 --mesh-voxels 0 \
                   --seed-file .lend/seeds4.npz > /tmp/r/s$s.log 2>&1
                 echo "seed $s done at $((SECONDS - t0)) s"; grep "^| " /tmp/r/s$s.log | tail -4
               done ;;
    fox-full) python3 benchmarks/keyframe_gpu.py .lend/fox --out /tmp/r/full --steps 3000 \
                --systems "$@" > /tmp/r/full.log 2>&1; tail -25 /tmp/r/full.log ;;
    *) echo "run: panoptic, fox-seeds or fox-full" >&2 ;;
  esac
  kill $snapper; wait $snapper; snap
}

case $verb in
  prepare) prepare ;;
  run) run "$@" ;;
  *) echo "usage: $0 prepare|run TASK" >&2; exit 2 ;;
esac
