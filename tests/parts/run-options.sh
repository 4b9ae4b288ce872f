#!/usr/bin/env bash
# run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL 'JSON' -- every part that run-all.sh ran (its
# RUNS_DIR) again with JSON merged into that run's own job options (`job-request.json`), and a
# Markdown row per part of the figures against the part opened by the program's tools
# (OUT_DIR/LABEL.md: mean / RMS / max gouge, and mean / RMS over the cells the scan measured, mm).
#
# The README's estimator table is made this way, e.g.
#   tests/parts/run-options.sh /tmp/parts /tmp/runs /tmp/opts fit-facet \
#     '{"reconstruct": {"estimator": "fit"}, "plan": {"finishing": {"pixel_model": "facet"}}}'
set -uo pipefail
export RUST_BACKTRACE=0
PARTS=${1:?usage: run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL JSON}
RUNS=${2:?usage: run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL JSON}
OUT=${3:?usage: run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL JSON}
LABEL=${4:?usage: run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL JSON}
MERGE=${5:?usage: run-options.sh PARTS_DIR RUNS_DIR OUT_DIR LABEL JSON}
BIN=${DEPTHMILL_BIN:-$(dirname "$0")/../../target/release/depthmill}
mkdir -p "$OUT"

for req in "$RUNS"/*/job-request.json; do
  [ -f "$req" ] || continue
  name=$(basename "$(dirname "$req")")
  part="$PARTS/$name.stl"
  [ -f "$part" ] || { echo "missing $part" >&2; continue; }
  opts="$OUT/$name.$LABEL.json"
  python3 - "$req" "$opts" "$MERGE" <<'PYEOF' || { echo "bad options for $name" >&2; continue; }
import json, sys
job = json.load(open(sys.argv[1]))
job.pop('input', None)
job.pop('name', None)
def merge(a, b):
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(a.get(k), dict):
            merge(a[k], v)
        else:
            a[k] = v
merge(job, json.loads(sys.argv[3]))
json.dump(job, open(sys.argv[2], 'w'), indent=1)
PYEOF
  # A part the first run refused (too large for the machine) is not run again.
  if [ ! -f "$RUNS/$name/artifacts/scan_report.json" ]; then
    echo "== $name: skipped, the first run made no job" >&2
    continue
  fi
  # The units the first run used (its scan report), so both runs read the file alike.
  units=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1])).get('units', {}).get('unit', 'mm'))" \
    "$RUNS/$name/artifacts/scan_report.json" 2>/dev/null || echo mm)
  echo "== $name ($units, $LABEL)" >&2
  rm -rf "$OUT/$name.$LABEL"
  "$BIN" demo --part "$part" --units "$units" --options "$opts" -o "$OUT/$name.$LABEL" > "$OUT/$name.$LABEL.log" 2>&1
done

python3 - "$OUT" "$LABEL" <<'PYEOF'
import json, os, sys
out, label = sys.argv[1], sys.argv[2]
rows = []
for d in sorted(os.listdir(out)):
    if not d.endswith('.' + label) or not os.path.isdir(os.path.join(out, d)):
        continue
    name = d[:-len(label) - 1]
    try:
        f = json.load(open(os.path.join(out, d, 'artifacts', 'report_json.json')))['figures']
        rows.append('| %s | %+.3f / %.3f / %.3f | %+.3f / %.3f |' % (
            name, f['part_opened_mean_mm'], f['part_opened_rms_mm'], f['part_opened_max_gouge_mm'],
            f['part_opened_measured_mean_mm'], f['part_opened_measured_rms_mm']))
    except Exception as e:
        rows.append(f'| {name} | failed: {e} | |')
hdr = f"| part | {label}: mean / RMS / max gouge mm | measured cells: mean / RMS mm |\n|---|---|---|"
open(os.path.join(out, label + '.md'), 'w').write(hdr + "\n" + "\n".join(rows) + "\n")
print(hdr); print("\n".join(rows))
PYEOF
