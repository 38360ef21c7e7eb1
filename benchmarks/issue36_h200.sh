#!/usr/bin/env bash
# Issue 36's rows still to measure on the GPU (docs/validation.md 'Rock that stands: the targets, case by
# case'). Two device calls, each within ~10 minutes of one H200:
#
#   bash benchmarks/issue36_h200.sh static            # the stiff groups of the static-friction matrix (~9 min)
#   bash benchmarks/issue36_h200.sh cost OLD_TREE     # cost per contact point against OLD_TREE (3997016) (~3 min)
#
# Records go to $OUT (the device call's folder) or benchmarks/results.
#
# static: the (width, stiffness) groups of the matrix that no 60 s record covers since the fixes: 0.2 m at
# the default stiffness (0.1 E L per point) and at 10 GPa/m, 1 m at 10 GPa/m (the other groups of `--subset full`
# were run for 60 s on the H200 or, on 2026-11-29, on the CPU; docs/validation.md). One process per group and start
# (6, side by side). These small models are launch-bound: ~0.5 ms per step alone, ~4,000 steps/s in all with 3-7
# processes on one H200 (records of 2026-11-28/29). 60 s needs 0.7-2.6 M steps per start, so the spans are cut so
# that every process takes ~290k steps (python -m benchmarks.static_friction --groups ... --estimate): 1 m 25 s,
# 0.2 m 11 s (10 GPa/m) and 6.8 s (default); creep over the last span / 6. Expected: ~1.75 M steps in all,
# ~7.5 min, plus ~1.5 min for the first process's kernel build. I36_GROUPS="W:SPEC,SECONDS ..." overrides the list (not GROUPS: bash reserves it).
#
# cost: benchmarks/scaling.py's jointed slope of 200,481 blocks at this tree and at OLD_TREE (an export of
# 3997016, the tree the issue was filed on), started together (300 settling steps, 50 timed; ~95 s each when run
# side by side on 2026-11-29): ns per contact point, new over old (the bound 1.2x).
set -u
PY=${PYTHON:-python3}   # the GPU image has python3 only
OUT=${OUT:-benchmarks/results}
D=$(date -u +%F)
mkdir -p "$OUT"

case "${1:-}" in
static)
    P="$OUT/$D-cuda0-static-friction-stiff"
    # one short run builds the kernels, so the processes load them from the cache
    "$PY" -m benchmarks.static_friction --device cuda:0 --groups 20:1e10Pa/m --duration 0.01 --starts plain \
        --out "$OUT/warm" > "$OUT/warm.log" 2>&1
    rm -f "$OUT/warm.md" "$OUT/warm.json"
    for s in plain settled; do
        for g in ${I36_GROUPS:-1:1e10Pa/m,25 0.2:1e10Pa/m,11 0.2:default,6.8}; do
            grp=${g%,*}; dur=${g#*,}; tag=$(echo "$grp" | tr ':/.' '___')
            "$PY" -m benchmarks.static_friction --device cuda:0 --groups "$grp" --duration "$dur" --starts "$s" \
                --out "$P-part-$tag-$s" > "$P-part-$tag-$s.log" 2>&1 &
        done
    done
    wait
    "$PY" -m benchmarks.static_friction --merge "$P"-part-*.json --out "$P" | head -8
    ;;
cost)
    OLD=$(cd "${2:?give the old tree (an export of 3997016: git archive 3997016 | tar -x -C DIR)}" && pwd)
    ABS=$(cd "$OUT" && pwd)
    # the old tree's rockwave.kernels is its kernels/ only through an install; run from its folder, the installed
    # (new) package would supply the new kernels, so link its own in
    [ -e "$OLD/rockwave/kernels" ] || ln -s ../kernels "$OLD/rockwave/kernels"
    set_args=(--set 'block_counts=[200000]' --set block_steps=50 --set block_settle=300 --set 'fluid_spacings=[]'
              --set 'coupled=[]' --set 'mem_fluid=[]' --set 'mem_blocks=[]')
    (cd "$OLD" && PYTHONPATH="$OLD${PYTHONPATH:+:$PYTHONPATH}" "$PY" -m benchmarks run --device cuda:0 --suite full --only scaling "${set_args[@]}" \
        --out "$ABS/$D-cuda0-full-scaling-200k-side-by-side-old-3997016.json" > "$ABS/cost-old.log" 2>&1) &
    "$PY" -m benchmarks run --device cuda:0 --suite full --only scaling "${set_args[@]}" \
        --out "$ABS/$D-cuda0-full-scaling-200k-side-by-side-new.json" > "$ABS/cost-new.log" 2>&1 &
    wait
    tail -3 "$ABS/cost-old.log" "$ABS/cost-new.log"
    ;;
*)
    echo "usage: bash benchmarks/issue36_h200.sh static | cost OLD_TREE" >&2
    exit 2
    ;;
esac
