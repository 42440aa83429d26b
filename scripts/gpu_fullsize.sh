#!/usr/bin/env bash
# WorldTree at NVIDIA-LS's real size on one CUDA GPU, stage by stage (issue #32): generate a 160-frame 480x270
# scene of the cost curve's layout, compute its priors while gsplat compiles, then train WorldTree depth 2 with the
# paper preset on CUDA and keep the run's small records. Meant for a lent GPU machine with a time limit, so the
# photometric fit and the tree layers may be shortened (STEPS, LAYERS); the warm-up, bundle adjustment, scaffold
# and test-pose stages keep the paper's length. Re-running resumes the run (and keeps the scene and priors).
#
#   OUT=DIR bash scripts/gpu_fullsize.sh          # env: STEPS (default 4000), LAYERS (2000,2000), F W H,
#                                                  #      LIMIT (seconds for the whole script), SS (supersample),
#                                                  #      PY (python), DEV (cuda), WORK (scratch folder)
#
# Packages the machine lacks may be carried as wheels in .whl/ (gsplat, submitit) and OpenCV with ximgproc as
# .gpu/cv2.tar.xz (an unpacked opencv-contrib-python-headless); they are installed into /tmp/site when present.
# Writes OUT/run.log, OUT/prep.log, OUT/gsplat_build.log, OUT/smi.csv (GPU memory and load every 2 s) and
# OUT/runfiles.tar (the run folder's JSON records: timing.json, metrics.json, the tree's layer and node reports).
set -u
T0=$(date +%s); el() { echo "[t=$(( $(date +%s) - T0 ))s] $*"; }
OUT=${OUT:?set OUT to the folder for the logs}
STEPS=${STEPS:-4000}; LAYERS=${LAYERS:-2000,2000}; F=${F:-160}; W=${W:-480}; H=${H:-270}; LIMIT=${LIMIT:-570}
PY=${PY:-python3}; DEV=${DEV:-cuda}; R=${WORK:-/tmp/w}
if [ -d .whl ] && [ "$DEV" != cpu ] && [ ! -d /tmp/site/gsplat ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  if [ -f .gpu/cv2.tar.xz ]; then tar -xJf .gpu/cv2.tar.xz -C /tmp/site || exit 1; fi
fi
# Hopper's own instructions for gsplat's kernels; the compile shares the cores with the priors below.
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=10
el "installed"; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
$PY -c "import torch, cv2; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'cv2', cv2.__version__, 'ximgproc', hasattr(cv2, 'ximgproc'))"
( t=$(date +%s); $PY -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" > "$OUT/gsplat_build.log" 2>&1
  echo "gsplat build s $(( $(date +%s) - t ))" >> "$OUT/gsplat_build.log" ) &
gsplat_job=$!
mkdir -p "$R"
if [ ! -f "$R/scenes/S/priors.done" ]; then
  $PY -m nvidia_ls.cli synth "$R/raw" --force --steps "$F" --width "$W" --height "$H" --motion slow_fast \
    --supersample "${SS:-1}" > "$R/synth.log" 2>&1 || { tail "$R/synth.log"; exit 1; }
  el "synth done"
  $PY -m nvidia_ls.cli build "$R/raw" -o "$R/scenes" --name S --force --poses "$R/raw/gt/poses_bounds.npy" \
    --frames "$F" > "$R/build.log" 2>&1 || { tail "$R/build.log"; exit 1; }
  el "build done"
  ( time $PY -m benchmarks.cli prep "$R/scenes/S" --downscale 1 ) > "$R/prep.log" 2>&1 || { tail "$R/prep.log"; exit 1; }
  el "prep done: $(grep real "$R/prep.log")"; touch "$R/scenes/S/priors.done"
fi
wait $gsplat_job; tail -2 "$OUT/gsplat_build.log"; el "gsplat ready"
nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv -l 2 > "$OUT/smi.csv" 2>&1 &
LIMIT=$(( LIMIT - $(date +%s) + T0 )); el "run limit $LIMIT s"
# SIGINT at the limit: the run checkpoints and a second call resumes it.
timeout -s INT "$LIMIT" $PY -m benchmarks.cli run --method worldtree --scene "$R/scenes/S" -o "$R/runs" --preset paper \
  --device "$DEV" --depth 2 --steps "$STEPS" --set "layer_steps=$LAYERS" --tag gpu > "$OUT/run.log" 2>&1
el "run exit $?"
cp "$R/prep.log" "$OUT/" 2>/dev/null
(cd "$R/runs" && find . -name "*.json" -size -2M | tar -cf "$OUT/runfiles.tar" -T -) 2>/dev/null
el "done"
