#!/usr/bin/env bash
# The family of generated scenes nothing is tuned to (issue #27): rig layouts, object paths, textures, camera
# orders and clip lengths of `nvls synth`, each rendered at 160x90, built into a scene with its exact poses and
# given exact priors (`nvls gt-priors`). Generation only: no training runs here.
#
#   bash scripts/tree_family.sh OUT [NAMES]      # NAMES: comma list of the names below, default all
#
# Writes OUT/raw/NAME (capture + ground truth), OUT/scenes/NAME (with gt_priors/) and OUT/scenes.txt (one
# scene folder per line). Resumable: a capture, scene or priors folder that exists is kept (each is written
# atomically, so an interrupted step leaves nothing behind and is redone).
set -euo pipefail
out=${1:?usage: scripts/tree_family.sh OUT [NAMES]}

# name: nvls synth options (160x90 and --depth are added to all). Seed 0 unless a name ends in _sN; the names
# say what varies.
family=(
  "rows_loop_40: --steps 40"
  "arc_straight_40: --rig arc --path straight --steps 40"
  "arc_straight_160: --rig arc --path straight --steps 160"
  "row_straight_40: --rig row --path straight --steps 40"
  "row_turning_40: --rig row --path turning --steps 40"
  "rows_turning_smooth_40: --path turning --texture smooth --steps 40"
  "rows_enter_leave_40: --path enter_leave --steps 40"
  "arc_enter_leave_shuffled_40: --rig arc --path enter_leave --camera-order shuffled --steps 40"
  "rows_straight_shuffled_160: --path straight --camera-order shuffled --steps 160"
  "row_loop_smooth_160: --rig row --texture smooth --steps 160"
  # 12 frames, as the real 12-frame protocol: depth 2's children hold 5 and 7 frames.
  "rows_loop_12: --steps 12"
  "row_straight_12: --rig row --path straight --steps 12"
  "arc_straight_12: --rig arc --path straight --steps 12"
  "row_turning_12: --rig row --path turning --steps 12"
  "rows_enter_leave_12: --path enter_leave --steps 12"
  # Held out (session 50): seeds, speeds, object counts, lenses and lengths that no measurement above chose.
  "rows_fast_40_s5: --motion fast --steps 40 --seed 5"
  "arc_slow_fast_40_s5: --rig arc --motion slow_fast --steps 40 --seed 5"
  "row_one_object_24_s5: --rig row --objects 1 --steps 24 --seed 5"
  "rows_turning_wide_40_s6: --path turning --rig-width 3.0 --fov-deg 50 --steps 40 --seed 6"
  "arc_enter_leave_24_s7: --rig arc --path enter_leave --steps 24 --seed 7"
  "row_smooth_shuffled_40_s7: --rig row --texture smooth --camera-order shuffled --steps 40 --seed 7"
  # The six held out above recorded by unmatched cameras (session 53): each camera's exposure within +-10 %,
  # its white balance within +-5 %, and 2 grey levels of sensor noise; the geometry and textures are theirs.
  "rows_fast_40_s5_cams: --motion fast --steps 40 --seed 5 --exposure 0.1 --noise 2"
  "arc_slow_fast_40_s5_cams: --rig arc --motion slow_fast --steps 40 --seed 5 --exposure 0.1 --noise 2"
  "row_one_object_24_s5_cams: --rig row --objects 1 --steps 24 --seed 5 --exposure 0.1 --noise 2"
  "rows_turning_wide_40_s6_cams: --path turning --rig-width 3.0 --fov-deg 50 --steps 40 --seed 6 --exposure 0.1 --noise 2"
  "arc_enter_leave_24_s7_cams: --rig arc --path enter_leave --steps 24 --seed 7 --exposure 0.1 --noise 2"
  "row_smooth_shuffled_40_s7_cams: --rig row --texture smooth --camera-order shuffled --steps 40 --seed 7 --exposure 0.1 --noise 2"
  # ... and with motion blur: the shutter open half of each step (session 53).
  "rows_fast_40_s5_blur: --motion fast --steps 40 --seed 5 --shutter 0.5"
  "arc_slow_fast_40_s5_blur: --rig arc --motion slow_fast --steps 40 --seed 5 --shutter 0.5"
  "row_one_object_24_s5_blur: --rig row --objects 1 --steps 24 --seed 5 --shutter 0.5"
  "rows_turning_wide_40_s6_blur: --path turning --rig-width 3.0 --fov-deg 50 --steps 40 --seed 6 --shutter 0.5"
  "arc_enter_leave_24_s7_blur: --rig arc --path enter_leave --steps 24 --seed 7 --shutter 0.5"
  "row_smooth_shuffled_40_s7_blur: --rig row --texture smooth --camera-order shuffled --steps 40 --seed 7 --shutter 0.5"
)
names=()
for entry in "${family[@]}"; do names+=("${entry%%:*}"); done
if [ -n "${2:-}" ]; then
  IFS=, read -r -a wanted <<<"$2"
  for w in "${wanted[@]}"; do
    [[ " ${names[*]} " == *" $w "* ]] || { echo "error: unknown scene $w; choose from ${names[*]}" >&2; exit 2; }
  done
else
  wanted=("${names[@]}")
fi

mkdir -p "$out/raw" "$out/scenes"
: >"$out/scenes.txt"
for entry in "${family[@]}"; do
  name=${entry%%:*} opts=${entry#*:}
  [[ " ${wanted[*]} " == *" $name "* ]] || continue
  raw="$out/raw/$name" scene="$out/scenes/$name"
  # shellcheck disable=SC2086  # opts is a list of options
  [ -d "$raw" ] || nvls synth "$raw" $opts --width 160 --height 90 --depth
  # The exact poses: the family varies what the reconstruction sees, not SfM (smooth textures give SfM little).
  steps=$(sed -n 's/.*--steps \([0-9]*\).*/\1/p' <<<"$opts")
  [ -d "$scene" ] || nvls build "$raw" -o "$out/scenes" --name "$name" --poses "$raw/gt/poses_bounds.npy" \
    --frames "$steps"
  [ -d "$scene/gt_priors" ] || nvls gt-priors "$raw" "$scene"
  echo "$scene" >>"$out/scenes.txt"
done
echo "scenes listed in $out/scenes.txt; priors of each under SCENE/gt_priors (masks/, tracks.npz, depth/)"
