#!/usr/bin/env bash
# Keep a long sweep's progress in the repository, so that it resumes on a fresh machine.
# A sweep folder's manifest.json, designs/ and digests/ (what `calendaring dataset` needs of
# each finished run, a few tens of kB a run; no run files, no packings) are copied to KEEP;
# with --restore they are copied back into a sweep folder, which `calendaring sweep` then
# resumes: a run with a complete digest counts as finished (calendaring/data/sweep.py).
# An `analysis compare` folder (no manifest.json) keeps its case records and analyses
# ([seed-*/]runs/*.record.h5, *.microstructure.json), which a rerun of the same compare
# command takes instead of running those cases again (analysis/compare.py). An `inverse
# refine` folder (or a folder of them, as benchmarks/refine_twins.py writes) keeps its state
# (refine.json, base.json, target.json, rounds/) and its round sweeps' manifests, designs
# and digests, from which a rerun of the same refine command goes on.
#   bash scripts/sweep-keep.sh RUNS KEEP              # e.g. /work/sweep-rve data/sweeps/rve
#   bash scripts/sweep-keep.sh --restore KEEP RUNS    # on a fresh machine, before the sweep
# Every file is written to a temporary name and renamed; files already in the destination
# are replaced only by newer ones, and a restore never replaces a file of the sweep folder.
set -euo pipefail
restore=0
if [ "${1:-}" = "--restore" ]; then restore=1; shift; fi
if [ $# -ne 2 ]; then
    echo "usage: sweep-keep.sh RUNS KEEP | sweep-keep.sh --restore KEEP RUNS" >&2
    exit 2
fi
src=$1 dst=$2
kind=sweep
if [ -n "$(find "$src" -maxdepth 2 -name refine.json -print -quit 2>/dev/null)" ]; then
    kind=refine
elif [ ! -f "$src/manifest.json" ]; then
    if [ -n "$(find "$src" -maxdepth 3 -path '*runs/*.record.h5' -print -quit 2>/dev/null)" ]
    then
        kind=compare
    else
        echo "sweep-keep: neither $src/manifest.json, $src/[seed-*/]runs/*.record.h5 nor" \
            "$src/[*/]refine.json found (not a sweep, compare, refine or keep folder)" >&2
        exit 2
    fi
fi
copied=0
copy() {  # copy() REL: src/REL -> dst/REL through a temporary name
    local rel=$1 to="$dst/$1"
    if [ -e "$to" ]; then
        if [ "$restore" = 1 ] || [ ! "$src/$rel" -nt "$to" ]; then return 0; fi
    fi
    mkdir -p "$(dirname "$to")"
    cp -p "$src/$rel" "$to.tmp-keep"
    mv -f "$to.tmp-keep" "$to"
    copied=$((copied + 1))
}
if [ "$kind" = sweep ]; then
    copy manifest.json
    for dir in designs digests; do
        [ -d "$src/$dir" ] || continue
        while IFS= read -r -d '' f; do
            case "$f" in *.tmp*) continue ;; esac
            copy "${f#"$src"/}"
        done < <(find "$src/$dir" -type f -print0)
    done
    n=0
    if [ -d "$dst/digests" ]; then n=$(find "$dst/digests" -name '*.h5' | wc -l); fi
    echo "sweep-keep: $copied files copied to $dst ($n digests there)"
elif [ "$kind" = refine ]; then
    # `inverse refine` folders (one, or one per twin below SRC): the state (*.json, rounds/)
    # and each round sweep's manifest, designs and digests; no run files or packings
    while IFS= read -r -d '' f; do
        case "$f" in */.*|*.tmp*|*.png|*.npz|*.pt|*.ckpt|*/rounds/*.h5) continue ;; esac  # rebuilt on resume
        copy "${f#"$src"/}"
    done < <(find "$src" -maxdepth 5 -type f \( -path '*/rounds/*' \
        -o -path '*/runs/manifest.json' -o -path '*/runs/designs/*' \
        -o -path '*/runs/digests/*' -o \( -name '*.json' ! -path '*/runs/*' \) \) -print0)
    n=$(find "$dst" -path '*runs/digests/*.h5' | wc -l)
    echo "sweep-keep: $copied files copied to $dst ($n digests there)"
else
    while IFS= read -r -d '' f; do
        case "$f" in */.*) continue ;; esac  # temporary files of an atomic write
        copy "${f#"$src"/}"
    done < <(find "$src" -maxdepth 3 -path '*runs/*' \( -name '*.record.h5' \
        -o -name '*.microstructure.json' \) -type f -print0)
    n=$(find "$dst" -maxdepth 3 -path '*runs/*.record.h5' | wc -l)
    echo "sweep-keep: $copied files copied to $dst ($n case records there)"
fi
# Kept files that git ignores would never be committed, and the sweep would be lost with the
# machine: refuse loudly instead of keeping them silently.
if [ "$restore" = 0 ] && git -C "$dst" rev-parse --is-inside-work-tree > /dev/null 2>&1; then
    ignored=$(cd "$dst" && find . -type f ! -name '*.tmp*' -print0 \
        | { git check-ignore -z --stdin --no-index || true; } | tr '\0' ' ')
    if [ -n "$ignored" ]; then
        echo "sweep-keep: git ignores files kept in $dst, so they would not be committed" \
            "(add a negated pattern to .gitignore): ${ignored:0:300}" >&2
        exit 3
    fi
fi
