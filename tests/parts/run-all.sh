#!/usr/bin/env bash
# run-all.sh PARTS_DIR OUT_DIR -- every part of the test set end to end (`depthmill demo --part`),
# then a Markdown table of the figures (OUT_DIR/table.md) for the README.
#
# Needs a release build (`cargo build --release --bin depthmill`) and the parts
# (`tests/parts/fetch.sh PARTS_DIR`). Units: the files' own where known; the unit-box CGAL models
# are read as inches (25.4 mm parts); the rest are decided by depthmill (`auto`).
# With TABLE_ONLY=1 it only writes the table from the runs already in OUT_DIR.
set -uo pipefail
export RUST_BACKTRACE=0
PARTS=${1:?usage: run-all.sh PARTS_DIR OUT_DIR}
OUT=${2:?usage: run-all.sh PARTS_DIR OUT_DIR}
BIN=${DEPTHMILL_BIN:-$(dirname "$0")/../../target/release/depthmill}
mkdir -p "$OUT"

# file|units
LIST="mesh-hinge.stl|auto
mesh-part1.stl|auto
mesh-flange.stl|auto
mesh-lever.stl|auto
mesh-t13-housing.stl|auto
mesh-m3x10-screw.stl|auto
mesh-torus.stl|auto
mesh-block-inch.stl|in
mesh-oblong.stl|auto
mesh-fandisk.stl|in
mesh-pinion.stl|in
mesh-couplingdown.stl|in
mesh-rotor.stl|in
mesh-joint.stl|in
mesh-anchor.stl|in
mesh-spool.stl|in
mesh-turbine.stl|in
mesh-bunny.stl|in
mesh-cheese.stl|auto
mesh-armadillo.stl|auto"

while IFS='|' read -r file units; do
  [ "${TABLE_ONLY:-0}" = 1 ] && break
  name=${file%.stl}
  [ -f "$PARTS/$file" ] || { echo "missing $PARTS/$file" >&2; continue; }
  echo "== $file ($units)" >&2
  args=(demo --part "$PARTS/$file" -o "$OUT/$name")
  [ "$units" != auto ] && args+=(--units "$units")
  start=$(date +%s)
  "$BIN" "${args[@]}" > "$OUT/$name.log" 2>&1
  echo "$? $(( $(date +%s) - start ))" > "$OUT/$name.rc"
done <<< "$LIST"

python3 - "$OUT" <<'PYEOF'
import json, os, sys
out = sys.argv[1]
rows = []
for name in sorted(f[:-3] for f in os.listdir(out) if f.endswith('.rc')):
    rc, secs = open(os.path.join(out, name + '.rc')).read().split()
    job_path = os.path.join(out, name, 'job.json')
    log = open(os.path.join(out, name + '.log')).read()
    if not os.path.exists(job_path):
        err = [l for l in log.splitlines() if l.startswith('Error')]
        msg = (err[-1] if err else log.strip().splitlines()[-1])
        if '"message":"' in msg:
            msg = msg.split('"message":"', 1)[1].split('","', 1)[0]
        rows.append(f"| {name} | refused: {msg[:400]} |" + " |" * 17)
        continue
    job = json.load(open(job_path))
    m = job.get('metrics', {})
    units = ''
    try:
        sr = json.load(open(os.path.join(out, name, 'artifacts', 'scan_report.json')))
        u = sr.get('units', {})
        units = f"{u.get('unit')} ({u.get('source')})"
    except Exception:
        pass
    f = lambda k, d=3: ('%.*f' % (d, m[k])) if k in m else '-'
    status = job.get('status')
    if status != 'succeeded':
        err = job.get('error') or {}
        rows.append(f"| {name} | {status}: {err.get('message', '')[:200]} |" + " |" * 17)
        continue
    tools = ''
    try:
        pr = json.load(open(os.path.join(out, name, 'artifacts', 'plan_report.json')))
        tools = ' + '.join(o['tool'] for o in pr['faces'][0]['operations'])
        if len(pr['faces']) > 1:
            tools += f" ({len(pr['faces'])} faces)"
    except Exception:
        pass
    faces = ''
    try:
        rr = json.load(open(os.path.join(out, name, 'artifacts', 'reconstruct_report.json')))
        fc = rr.get('face_choice')
        if fc:
            faces = ', '.join(f"{c['face']} +{c['gain_pct']:.1f}" for c in fc['chosen'])
            faces += f" ({fc['covered_pct']:.1f} reached, {fc['unreached_pct']:.1f} from none)"
        else:
            faces = ', '.join(f['face'] for f in rr.get('faces', []))
    except Exception:
        pass
    rows.append(f"| {name} | {units} | {faces} | {tools} | {f('scan_silhouette_coverage_pct', 1)} | {f('coverage_pct', 1)} | {f('part_mean_mm')} | {f('part_rms_mm')} | {f('part_max_gouge_mm')} | {f('part_off_walls_max_gouge_mm')} | {f('part_off_walls_rms_mm')} | {f('preview_rms_mm')} | {f('part_opened_mean_mm', 4)} | {f('part_opened_rms_mm', 4)} | {f('part_opened_max_gouge_mm', 4)} | {f('max_gouge_mm')} | {f('cycle_time_s', 0)} | {f('cycle_time_no_adaptive_s', 0)} | {float(secs):.0f} |")
hdr = "| part | units read | faces (surface share each adds, %) | tools | silhouette seen % | depth-map coverage % | mean vs part mm | RMS vs part mm | max gouge vs part mm | max gouge off walls mm | RMS off walls mm | RMS vs tools' surface mm | mean vs part opened mm | RMS vs part opened mm | max gouge vs part opened mm | max gouge vs target (one face) or original part (several) mm | cycle s (adaptive) | cycle s (none) | wall s |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
open(os.path.join(out, 'table.md'), 'w').write(hdr + "\n" + "\n".join(rows) + "\n")
print(hdr); print("\n".join(rows))
PYEOF
