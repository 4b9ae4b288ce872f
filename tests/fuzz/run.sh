#!/usr/bin/env bash
# Coverage-guided fuzzing of the readers and the G-code interpreter with libFuzzer
# (libfuzzer-sys, no sanitizer: the stable toolchain is enough). See README.md.
#
#   tests/fuzz/run.sh build                      instrumented release build of every target
#   tests/fuzz/run.sh smoke SECONDS              every target SECONDS s from the kept corpus (CI);
#                                                new inputs go to a scratch folder, a crash fails
#   tests/fuzz/run.sh run TARGET [ARGS...]       one target, growing its kept corpus; ARGS go to
#                                                libFuzzer (-runs=N, -max_total_time=S, -jobs=N)
#   tests/fuzz/run.sh campaign RUNS [PARALLEL]   every target RUNS executions (PARALLEL targets at
#                                                a time, default 2), then its corpus minimised;
#                                                prints one line of figures per target
#   tests/fuzz/run.sh minimise                   every target's kept corpus minimised
#
# CARGO_TARGET_DIR (default: target/fuzz in the repository) holds the build.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
target_dir="${CARGO_TARGET_DIR:-$repo/target}/fuzz"
host="$(rustc -vV | sed -n 's/^host: //p')"
bin_dir="$target_dir/$host/release"
targets=(cloud ply xyz stl png npy tool machine_toml gcode job_json report_gcode)
# Inputs up to 64 KiB; an input that runs 10 s or needs 2 GiB is a finding.
fuzz_args=(-max_len=65536 -timeout=10 -rss_limit_mb=2048 -print_final_stats=1)

build() {
    # The flags cargo-fuzz passes with `--sanitizer none`: SanitizerCoverage (8-bit counters,
    # PC table, comparison tracing) feeding libFuzzer. `--target` keeps them off build scripts
    # and proc macros, which run on the host.
    RUSTFLAGS="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares -Cllvm-args=-sanitizer-coverage-stack-depth \
--cfg fuzzing -Cdebug-assertions -Coverflow-checks" \
        CARGO_TARGET_DIR="$target_dir" \
        cargo build --release --locked --manifest-path "$here/Cargo.toml" --target "$host" --bins
}

corpus() { mkdir -p "$here/corpus/$1"; echo "$here/corpus/$1"; }

# Keeps a target's corpus small: the fewest inputs that together reach the same coverage.
minimise() {
    local t="$1" kept="$here/corpus/$1"
    rm -rf "$logs/$t.min"
    mkdir -p "$logs/$t.min"
    if "$bin_dir/$t" "${fuzz_args[@]}" -set_cover_merge=1 "$logs/$t.min" "$(corpus "$t")" \
        >"$logs/$t.merge.log" 2>&1; then
        rm -rf "$kept" && mv "$logs/$t.min" "$kept"
    fi
}

case "${1:-}" in
build)
    build
    ;;
smoke)
    seconds="${2:?seconds per target}"
    build
    scratch="$(mktemp -d)"
    trap 'rm -rf "$scratch"' EXIT
    for t in "${targets[@]}"; do
        mkdir -p "$scratch/$t/new" "$scratch/$t/crashes"
        # The first folder takes what the run finds; the kept corpus is only read.
        if ! "$bin_dir/$t" "${fuzz_args[@]}" -max_total_time="$seconds" \
            -artifact_prefix="$scratch/$t/crashes/" "$scratch/$t/new" "$(corpus "$t")" \
            >"$scratch/$t/log" 2>&1; then
            tail -n 60 "$scratch/$t/log" >&2
            for f in "$scratch/$t/crashes"/*; do
                [ -e "$f" ] && { echo "crashing input ($f), base64:" >&2; base64 -w0 "$f" >&2; echo >&2; }
            done
            echo "fuzz smoke: $t failed" >&2
            exit 1
        fi
        grep -E '^stat::number_of_executed_units' "$scratch/$t/log" | sed "s/^/$t /"
    done
    ;;
run)
    t="${2:?target}"
    shift 2
    build
    mkdir -p "$repo/target/fuzz-artifacts/$t"
    exec "$bin_dir/$t" "${fuzz_args[@]}" -artifact_prefix="$repo/target/fuzz-artifacts/$t/" "$@" "$(corpus "$t")"
    ;;
campaign)
    runs="${2:?executions per target}"
    parallel="${3:-2}"
    build
    logs="$repo/target/fuzz-logs"
    mkdir -p "$logs"
    one() {
        t="$1"
        mkdir -p "$repo/target/fuzz-artifacts/$t"
        status=ok
        "$bin_dir/$t" "${fuzz_args[@]}" -runs="$runs" -artifact_prefix="$repo/target/fuzz-artifacts/$t/" \
            "$(corpus "$t")" >"$logs/$t.log" 2>&1 || status=FAILED
        minimise "$t"
        execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$logs/$t.log")
        secs=$(sed -n 's/^Done [0-9]* runs in \([0-9]*\) second.*/\1/p' "$logs/$t.log")
        rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$logs/$t.log")
        cov=$(grep -oE 'cov: [0-9]+' "$logs/$t.log" | tail -1)
        echo "$t: $status, ${execs:-?} executions in ${secs:-?} s (${rate:-?}/s), ${cov:-cov: ?}, corpus $(ls "$(corpus "$t")" | wc -l) inputs"
    }
    export -f one corpus minimise
    export bin_dir here repo runs logs
    export fuzz_args_str="${fuzz_args[*]}"
    printf '%s\n' "${targets[@]}" | xargs -P "$parallel" -I{} bash -c 'fuzz_args=($fuzz_args_str); one {}'
    ;;
minimise)
    build
    logs="$repo/target/fuzz-logs"
    mkdir -p "$logs"
    for t in "${targets[@]}"; do
        minimise "$t"
        echo "$t: corpus $(ls "$(corpus "$t")" | wc -l) inputs, $(du -sh "$(corpus "$t")" | cut -f1)"
    done
    ;;
*)
    sed -n '2,17p' "$0" >&2
    exit 2
    ;;
esac
