#!/usr/bin/env bash
# Side by side: the machine service's G-code interpreter against LinuxCNC's standalone interpreter
# rs274 (Debian package linuxcnc-uspace) on the same 1M-block finishing program.
#
#   services/machine/scripts/compare_rs274.sh [PROGRAM.ngc TOOL.tbl]
#
# Without arguments a finishing program in the CAM service's LinuxCNC style is generated
# (BLOCKS=1000000 lines: raster passes of modal "X.. Z.." moves, a G2/G3 semicircle between passes).
# Tool tables are in inches (the standalone rs274 has no INI file).
#
# 1. times rs274 from the shell (user+sys CPU and wall, best of RUNS=3), output to /dev/null;
# 2. runs the interp bench on the same files, which times ours and rs274 again in one process,
#    prints the CPU-throughput ratio against the >= 10x target, and checks that both runs make
#    the same moves (end points within 1e-4 mm, same arcs).
#
# Env: BLOCKS, RUNS, DEPTHMILL_MANIFEST (Cargo.toml to build with; default the workspace root),
# CARGO_TARGET_DIR (passed through to cargo).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
manifest="${DEPTHMILL_MANIFEST:-$here/../../Cargo.toml}"
blocks="${BLOCKS:-1000000}"
runs="${RUNS:-3}"

if ! command -v rs274 >/dev/null 2>&1; then
    echo "rs274 not found on PATH: apt-get install linuxcnc-uspace" >&2
    exit 2
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

if [[ $# -ge 2 ]]; then
    prog="$1"
    tbl="$2"
else
    prog="$work/finishing.ngc"
    tbl="$work/tool.tbl"
    printf 'T1 P1 Z1.0 D0.125 ;ball-3\n' >"$tbl"
    awk -v blocks="$blocks" 'BEGIN {
        n = 0
        split("%|(depthmill finishing benchmark)|G21 G90 G17 G94 G40 G49 G80|G64 P0.0100|G53 G0 Z0.0000|T1 M6|S2000 M3|M8|G43 H1|G0 X0.0000 Y0.0000|Z5.0000|G1 Z-0.5000 F300.0000", h, "|")
        for (k = 1; k <= 12; k++) { print h[k]; if (h[k] != "%") n++ }
        per = 1000; step = 0.2; pass = 0
        while (n + 5 < blocks) {
            y = pass * step; fwd = (pass % 2 == 0)
            pts = blocks - 5 - n; if (pts > per) pts = per
            for (i = 1; i <= pts; i++) {
                t = i / per; x = fwd ? 50 * t : 50 * (1 - t)
                z = -0.5 + 0.3 * sin(x * 0.21) * cos(y * 0.17) - 0.05 * cos(x * 0.05 + y * 0.03)
                printf "%sX%.4f Z%.4f\n", (i == 1 && pass > 0) ? "G1 " : "", x, z
                n++
            }
            if (pts < per || n + 6 > blocks) break
            printf "G%d X%.4f Y%.4f I0.0000 J%.4f\n", fwd ? 3 : 2, fwd ? 50 : 0, y + step, step / 2
            n++; pass++
        }
        print "G0 Z5.0000"; print "M5"; print "M9"; print "G53 G0 Z0.0000"; print "M30"; print "%"
    }' >"$prog"
fi

lines=$(wc -l <"$prog")
echo "program: $prog ($lines lines)"

# rs274 from the shell. Its tool table lives in a memory-mapped $HOME/.tool.mmap: private HOME.
mkdir -p "$work/home"
best_cpu=""
best_wall=""
TIMEFORMAT='%U %S %R'
for _ in $(seq "$runs"); do
    t=$( { time HOME="$work/home" rs274 -t "$tbl" -b -g "$prog" /dev/null 2>"$work/rs274.err" >/dev/null; } 2>&1 )
    if grep -v -x 'executing' "$work/rs274.err" | grep -q .; then
        echo "rs274 reported an error:" >&2
        cat "$work/rs274.err" >&2
        exit 1
    fi
    read -r user sys wall <<<"$t"
    cpu=$(awk -v u="$user" -v s="$sys" 'BEGIN { printf "%.3f", u + s }')
    if [[ -z "$best_cpu" ]] || awk -v a="$cpu" -v b="$best_cpu" 'BEGIN { exit !(a < b) }'; then best_cpu="$cpu"; fi
    if [[ -z "$best_wall" ]] || awk -v a="$wall" -v b="$best_wall" 'BEGIN { exit !(a < b) }'; then best_wall="$wall"; fi
done
awk -v c="$best_cpu" -v w="$best_wall" -v n="$lines" 'BEGIN {
    printf "rs274 (shell): best of runs: %.3f s CPU (%.3f s wall) -> %.2f M lines/s CPU\n", c, w, n / c / 1e6 }'

# Ours (and rs274 again, and the agreement check) in the bench binary.
cargo bench --manifest-path "$manifest" -p depthmill-machine --bench interp -- \
    --program "$prog" --tool-table "$tbl" --runs "$runs"
