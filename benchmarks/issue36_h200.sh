#!/usr/bin/env bash
# Issue 36's rows still to measure on the GPU (docs/validation.md 'Rock that stands: the targets, case by
# case'). Two device calls, each within ~10 minutes of one H200:
#
#   bash benchmarks/issue36_h200.sh static            # the stiff groups of the static-friction matrix
#   bash benchmarks/issue36_h200.sh cost OLD_TREE     # cost per contact point, this tree against OLD_TREE (3997016)
#
# Records go to $OUT (the device call's folder) or benchmarks/results.
#
# static: the six (width, stiffness) groups of the matrix that no record has measured since the fixes
# (0.2 m and 1 m at the default stiffness and at 10 GPa/m, 5 m and 20 m at 10 GPa/m), one process per group and
# start (12, side by side; small models are launch-bound: ~0.5 ms per step alone, ~4,000 steps/s in all with 3-7
# processes on one H200, records of 2026-11-28/29). Spans are cut so that every process takes ~155k steps
# (python -m benchmarks.static_friction --groups ... --estimate): 20 m 60 s, 5 m 30 s, 1 m 13 s (10 GPa/m) and
# 18 s (default), 0.2 m 6 s (10 GPa/m) and 3.6 s (default); creep over the last min(10 s, span / 6). Expected:
# ~1.9 M steps in all, ~8 min, plus ~1.5 min for the first process's kernel build.
#
# cost: benchmarks/scaling.py's jointed slope of 200,481 blocks at this tree and at OLD_TREE (an export of
# 3997016, the tree the issue was filed on), started together (300 settling steps, 50 timed; ~95 s each when run
# side by side on 2026-11-29): ns per contact point, new over old (the bound 1.2x).
set -u
OUT=${OUT:-benchmarks/results}
D=$(date -u +%F)
mkdir -p "$OUT"

case "${1:-}" in
static)
    P="$OUT/$D-cuda0-static-friction-stiff"
    # one short run builds the kernels, so the 12 processes load them from the cache
    python -m benchmarks.static_friction --device cuda:0 --groups 20:1e10Pa/m --duration 0.01 --starts plain \
        --out "$OUT/warm" > "$OUT/warm.log" 2>&1
    rm -f "$OUT/warm.md" "$OUT/warm.json"
    for s in plain settled; do
        for g in 20:1e10Pa/m,60 5:1e10Pa/m,30 1:1e10Pa/m,13 1:default,18 0.2:1e10Pa/m,6 0.2:default,3.6; do
            grp=${g%,*}; dur=${g#*,}; tag=$(echo "$grp" | tr ':/.' '___')
            python -m benchmarks.static_friction --device cuda:0 --groups "$grp" --duration "$dur" --starts "$s" \
                --out "$P-part-$tag-$s" > "$P-part-$tag-$s.log" 2>&1 &
        done
    done
    wait
    python -m benchmarks.static_friction --merge "$P"-part-*.json --out "$P" | head -8
    ;;
cost)
    OLD=$(cd "${2:?give the old tree (an export of 3997016: git archive 3997016 | tar -x -C DIR)}" && pwd)
    ABS=$(cd "$OUT" && pwd)
    # the old tree's rockwave.kernels is its kernels/ only through an install; run from its folder, the installed
    # (new) package would supply the new kernels, so link its own in
    [ -e "$OLD/rockwave/kernels" ] || ln -s ../kernels "$OLD/rockwave/kernels"
    set_args=(--set 'block_counts=[200000]' --set block_steps=50 --set block_settle=300 --set 'fluid_spacings=[]'
              --set 'coupled=[]' --set 'mem_fluid=[]' --set 'mem_blocks=[]')
    (cd "$OLD" && PYTHONPATH="$OLD" python -m benchmarks run --device cuda:0 --suite full --only scaling "${set_args[@]}" \
        --out "$ABS/$D-cuda0-full-scaling-200k-side-by-side-old-3997016.json" > "$ABS/cost-old.log" 2>&1) &
    python -m benchmarks run --device cuda:0 --suite full --only scaling "${set_args[@]}" \
        --out "$ABS/$D-cuda0-full-scaling-200k-side-by-side-new.json" > "$ABS/cost-new.log" 2>&1 &
    wait
    tail -3 "$ABS/cost-old.log" "$ABS/cost-new.log"
    ;;
*)
    echo "usage: bash benchmarks/issue36_h200.sh static | cost OLD_TREE" >&2
    exit 2
    ;;
esac
