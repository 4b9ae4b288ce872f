#!/usr/bin/env bash
# Wall time of `depthmill demo` per stage, release build, RUNS times (default 3).
# Target: the whole demo under 20 s on a 2-core machine (the table turning in real time). Prints each run's stage timings, the
# part of the scan spent waiting for the rotary table (real time) and the wall time.
set -euo pipefail
cd "$(dirname "$0")/../../.."
runs=${1:-3}
cargo build --release --bin depthmill
for i in $(seq 1 "$runs"); do
    out=$(mktemp -d)
    target/release/depthmill demo -o "$out" | grep -E "stage timings|demo wall time|^scan:"
    python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(f\"  scan: {r['table_wait_s']:.1f} s waiting for the table, {r['frames']} frames, simulated scan time {r['scan_time_s']:.1f} s\")" "$out/artifacts/scan_report.json" || true
    rm -rf "$out"
done
