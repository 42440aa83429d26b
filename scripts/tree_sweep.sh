#!/usr/bin/env bash
# Does the tree beat its root? (issue #27, docs/worldtree_method.md "The tree against its root"): the `tree`
# grid (the root alone, depths 1 and 2, --depth auto) over the generated family of scripts/tree_family.sh,
# each scene with its exact priors (the root trained once per scene: --share-root), then one table per scene and
# one over all of them.
#
#   bash scripts/tree_sweep.sh FAMILY_OUT RUNS_OUT [NAMES] [-- extra wtbench sweep options]
#
# FAMILY_OUT is the folder scripts/tree_family.sh wrote (its scenes/NAME folders); NAMES a comma list (default:
# every scene listed in FAMILY_OUT/scenes.txt). Resumable: finished runs are skipped by `wtbench sweep`.
set -euo pipefail
fam=${1:?usage: scripts/tree_sweep.sh FAMILY_OUT RUNS_OUT [NAMES] [-- sweep options]}
out=${2:?usage: scripts/tree_sweep.sh FAMILY_OUT RUNS_OUT [NAMES] [-- sweep options]}
shift 2
names=""
if [ $# -gt 0 ] && [ "$1" != "--" ]; then names=$1; shift; fi
[ "${1:-}" = "--" ] && shift
if [ -n "$names" ]; then
  IFS=, read -r -a scenes <<<"$names"
else
  mapfile -t scenes < <(xargs -n1 basename <"$fam/scenes.txt")
fi
mkdir -p "$out"
for name in "${scenes[@]}"; do
  scene="$fam/scenes/$name"
  [ -f "$scene/cameras.json" ] || { echo "error: $scene is not a scene; run scripts/tree_family.sh $fam first" >&2; exit 2; }
  wtbench sweep --grid tree --share-root --scenes "$scene" --preset quick --device cpu -o "$out" \
    --masks "$scene/gt_priors/masks" --tracks "$scene/gt_priors/tracks.npz" --depth-maps "$scene/gt_priors/depth" "$@"
done
wtbench table "$out" -o "$out/table.csv"
