#!/usr/bin/env bash
# Reference run for the rasterisation benchmark: CloudCompare's Rasterize (max Z per cell).
#
# Usage:
#   scripts/compare_cloudcompare.sh
#       Runs the benchmark (benches/raster.rs). It generates the 10^7-point cloud, times
#       rasterize_max, fill_holes and coverage, writes the cloud as PLY and times CloudCompare on
#       it in the same run, then checks CloudCompare's cells against ours on a smaller cloud.
#   scripts/compare_cloudcompare.sh CLOUD.ply [GRID_STEP_MM] [RUNS] [OUT_DIR]
#       Times CloudCompare alone on CLOUD.ply (binary or ASCII PLY with x, y, z): best of RUNS
#       (default 3) load-only runs and load + rasterize runs; the rasterisation time is the
#       difference (CloudCompare's log has no per-step timings). Then saves the raster cloud (one
#       point per non-empty cell at its centre, z = max) to OUT_DIR/raster.ply (default: a new
#       temporary directory).
#
# CloudCompare's convention: the cloud's bounding-box minimum is the centre of cell 0
# (depthmill's grid puts the corner of cell 0 at the ROI minimum; shift by half a pixel to compare).
# CloudCompare runs headless with QT_QPA_PLATFORM=offscreen (no X server or xvfb needed).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

if ! command -v CloudCompare >/dev/null 2>&1; then
    echo "CloudCompare is not installed; on Debian/Ubuntu: apt-get install -y cloudcompare" >&2
    exit 2
fi

if [[ $# -eq 0 ]]; then
    cd "$here/.."
    exec cargo bench -p depthmill-geometry --bench raster
fi

cloud="$(realpath "$1")"
step="${2:-0.1}"
runs="${3:-3}"
out_dir="${4:-$(mktemp -d)}"
mkdir -p "$out_dir"
[[ -f "$cloud" ]] || { echo "no such file: $cloud" >&2; exit 1; }

cc() {
    # -AUTO_SAVE OFF: nothing is written unless asked; -SILENT: no dialogs.
    (cd "$out_dir" && QT_QPA_PLATFORM=offscreen CloudCompare -SILENT -AUTO_SAVE OFF -NO_TIMESTAMP "$@")
}

# Best wall time in ms of `cc "$@"` over $runs runs; the last run's log goes to $out_dir/last.log.
best_ms() {
    local best="" t0 t1 ms
    for ((i = 0; i < runs; i++)); do
        t0=$(date +%s%N)
        cc "$@" >"$out_dir/last.log" 2>&1
        t1=$(date +%s%N)
        ms=$(((t1 - t0) / 1000000))
        if [[ -z "$best" || $ms -lt $best ]]; then best=$ms; fi
    done
    echo "$best"
}

echo "load average: $(cut -d' ' -f1-3 /proc/loadavg)"
load=$(best_ms -O "$cloud")
points=$(grep -o 'with [0-9]* points' "$out_dir/last.log" | head -1 || true)
full=$(best_ms -O "$cloud" -RASTERIZE -GRID_STEP "$step" -PROJ MAX)
grid=$(grep -m1 '^Grid size' "$out_dir/last.log" || echo "grid size not logged")
echo "cloud: $cloud ($points)"
echo "load only:        $load ms (best of $runs)"
echo "load + rasterize: $full ms (best of $runs; $grid)"
echo "rasterize:        $((full - load)) ms (difference)"

cc -C_EXPORT_FMT PLY -O "$cloud" -RASTERIZE -GRID_STEP "$step" -PROJ MAX -OUTPUT_CLOUD \
    -SAVE_CLOUDS FILE "$out_dir/raster.ply" >"$out_dir/save.log" 2>&1
echo "raster cloud (cell centres, z = max): $out_dir/raster.ply"
