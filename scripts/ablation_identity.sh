#!/usr/bin/env bash
# Is the ablation table unchanged by a refactor? (issue #29, docs/adding_a_method.md): the paper-ablation grid
# (9 runs) at the smoke preset on one generated scene, seed 0, with the code of BEFORE (a git revision) and of
# this checkout, then every quality figure, Gaussian count, scaffold and tree size compared value for value.
#
#   bash scripts/ablation_identity.sh BEFORE OUT     # e.g. bash scripts/ablation_identity.sh 6f90daa /tmp/abl
#
# BEFORE is checked out as a detached worktree under OUT (removed at the end); the scene is generated and
# built once by this checkout and given to both. Exit 1 when a value differs. Resumable (finished runs skipped).
set -euo pipefail
before=${1:?usage: scripts/ablation_identity.sh BEFORE OUT}
out=${2:?usage: scripts/ablation_identity.sh BEFORE OUT}
here=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out"
out=$(cd "$out" && pwd)
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
if [ ! -f "$out/scenes/Abl/manifest.json" ]; then
  (cd "$here" && PYTHONPATH="$here" nvls synth "$out/raw/Abl" --steps 24 --width 160 --height 90 --motion slow_fast --force)
  (cd "$here" && PYTHONPATH="$here" nvls build "$out/raw/Abl" -o "$out/scenes" --force)
fi
tree="$out/before-src"
[ -d "$tree" ] || git -C "$here" worktree add -q --detach "$tree" "$before"
trap 'git -C "$here" worktree remove --force "$tree" 2>/dev/null || true' EXIT
for side in before after; do
  src=$here; [ "$side" = before ] && src=$tree
  (cd "$src" && PYTHONPATH="$src" wtbench sweep --grid paper-ablation --scenes "$out/scenes/Abl" --preset smoke \
     --device cpu -o "$out/runs_$side" && PYTHONPATH="$src" wtbench table "$out/runs_$side" -o "$out/table_$side.csv")
done
python3 - "$out" <<'PY'
import csv, sys
out = sys.argv[1]
keep = ("psnr", "ssim", "mpsnr", "mssim", "n_gaussians", "n_scaffold_nodes", "n_tree_nodes")
def load(side):
    rows = csv.DictReader(open(f"{out}/table_{side}_long.csv"))
    return {(r["configuration"], r["metric"]): r["value"] for r in rows if r["metric"] in keep}
b, a = load("before"), load("after")
bad = sorted(k for k in b.keys() | a.keys() if b.get(k) != a.get(k))
for k in bad:
    print(f"differs: {k[0]} {k[1]}: before {b.get(k)} after {a.get(k)}")
print(f"{len(b) - len(bad)} of {len(b | a)} values identical ({len({c for c, _ in b})} configurations)")
sys.exit(1 if bad else 0)
PY
