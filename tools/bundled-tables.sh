#!/usr/bin/env bash
# Runs every bundled spec in experiments/ with a binary and writes its tables under OUT, so
# that two builds can be compared table by table (a behaviour-preserving change must leave
# every table byte-identical).
#
#   tools/bundled-tables.sh write BIN OUT [RUNS]   # RUNS per cell (default 20)
#   tools/bundled-tables.sh compare OUT_A OUT_B    # cmp every .parquet; exit 1 on a difference
#
# Specs with outside filters are simulated (`kfmc simulate`): their world tables are what a
# build produces for them without the outside program.
set -euo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
write)
    bin=$2 out=$3 runs=${4:-20}
    mkdir -p "$out"
    for spec in experiments/*.toml; do
        name=$(basename "$spec" .toml)
        # A binary older than a spec (keys it does not know) refuses it with exit 2: the spec
        # is skipped and `compare` reports its tables as present on one side only.
        if ! "$bin" validate "$spec" >/dev/null 2>&1; then
            echo "skipped $name: $bin refuses the spec" >&2
            continue
        fi
        cmd=(run --quiet --force)
        if grep -q 'kind *= *"external"' "$spec"; then
            cmd=(simulate)
        fi
        # A spec whose [[consistency.subsets]] need more runs than RUNS is refused with exit 2
        # and runs with its own.
        rc=0
        "$bin" "${cmd[@]}" "$spec" --out "$out/$name" --runs "$runs" >/dev/null 2>&1 || rc=$?
        if [ "$rc" = 2 ]; then
            echo "$name: with its own runs (its subsets need more than $runs)" >&2
            "$bin" "${cmd[@]}" "$spec" --out "$out/$name" >/dev/null
        elif [ "$rc" != 0 ]; then
            echo "$name: $bin ${cmd[*]} exited with $rc" >&2
            exit "$rc"
        fi
    done
    ;;
compare)
    a=$2 b=$3 status=0 n=0
    while IFS= read -r f; do
        rel=${f#"$a"/}
        n=$((n + 1))
        if [ ! -f "$b/$rel" ]; then
            echo "only in $a: $rel"; status=1
        elif ! cmp -s "$f" "$b/$rel"; then
            echo "differs: $rel"; status=1
        fi
    done < <(find "$a" -name '*.parquet' | sort)
    while IFS= read -r f; do
        rel=${f#"$b"/}
        [ -f "$a/$rel" ] || { echo "only in $b: $rel"; status=1; }
    done < <(find "$b" -name '*.parquet' | sort)
    echo "$n tables compared"
    exit $status
    ;;
*)
    sed -n '2,10p' "$0"; exit 2 ;;
esac
