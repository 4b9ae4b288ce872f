#!/usr/bin/env python3
"""Compare depthmill's `plan` with LinuxCNC's image-to-gcode on the same depth image.

What it compares
----------------
The project's target is `depthmill plan` running >= 50x faster than LinuxCNC's
image-to-gcode making the comparable program (same tools, step-over and
roughing step-down) from the same image.  This script

1. writes a deterministic N x N 8-bit grayscale PNG of a smooth relief (a few
   Gaussian bumps plus a sine ripple, using the full 0..255 range) into a temp
   dir.  Pixel size 0.1 mm, depth 20 mm: white is the top (Z 0), black is
   20 mm below (Z -20) -- image-to-gcode's convention with "invert" off
   (z = pixel/255*depth - depth), given to depthmill as
   `--pixel-mm 0.1 --z-min-mm=-20 --z-max-mm 0`;
2. times image-to-gcode (wall clock of a child /usr/bin/python3 process, so
   it includes Python start-up, the image read and writing the program):
   * finishing: 3 mm ball end, step-over 3 pixels (0.3 mm), rows only,
     alternating direction (zigzag, as depthmill's raster_x), tolerance
     0.01 mm, roughing off (roughing_offset 0; the script roughs only
     `if self.roughing_delta and self.roughing_offset`);
   * roughing: 6 mm flat end, roughing_offset 0.3 mm (stock to leave),
     roughing_depth 2.0 mm (step-down), step-over 24 pixels (2.4 mm, the
     0.4 x D that depthmill uses for roughing; `--rough-step-px` changes it).
     image-to-gcode always follows its roughing passes with a finishing pass
     of the same tool and step-over, which it cannot switch off.  By default
     (`--rough-mode skip-finish`) the child replaces Converter.one_pass by a
     wrapper that skips that one final pass (the one run with self.ro == 0
     after roughing), so the figure is roughing alone: the dilation by the
     roughing offset plus the step-down passes, nothing of the program's
     algorithm changed.  `--rough-mode subtract` instead times the full
     roughing+finishing run and subtracts a separate finishing-only run of
     the same tool and step-over (costs a third run; noisier);
3. times `target/release/depthmill plan IMAGE.png --pixel-mm 0.1
   --z-min-mm=-20 --z-max-mm 0 --options plan.json -o out.ngc` (wall clock of
   the whole process: image read, roughing with flat-6, finishing with
   ball-3, tool compensation, holder checks, link/arc fitting, the
   stock-removal preview, writing the program, report and preview PNGs), and
   reads the per-step times from out.report.json (`timings_s`);
4. prints a table of time and program lines ("blocks") for each, the ratio
   (image-to-gcode finishing + roughing) / depthmill total, and finishing vs
   finishing: image-to-gcode finishing against depthmill's `finishing` step
   (the finishing tool's compensation and passes; the roughing, with its own
   tool's compensation, runs beside it).

How to run
----------
    python3 services/cam/scripts/compare_image_to_gcode.py [--size 2000] [--skip-roughing]

from the repository root (or anywhere: paths are found from this file).
Other options: --keep (keep the temp dir and print it), --rough-mode,
--rough-step-px, --skip-depthmill, --skip-i2g.  At 2000 x 2000 image-to-gcode
takes minutes; --size 400 is a quick check.  For reference, on this 2-core
machine (while a cargo test ran beside it) image-to-gcode took 80 s
(190,672 lines) for the finishing and 67 s (285,283 lines) for the roughing
at 2000 x 2000, and 3.2 s / 2.9 s at 400 x 400.

What it needs
-------------
* `apt-get install linuxcnc-uspace python3-pil` -- /usr/bin/image-to-gcode
  and Debian's python3-numpy (a dependency) and python3-pil (only a
  "Recommends" of linuxcnc-uspace, so name it when installing with
  --no-install-recommends).  image-to-gcode runs under /usr/bin/python3; the
  pyenv python3 on PATH lacks PIL, so this script re-executes itself under
  /usr/bin/python3 when numpy or PIL is missing.
* a release build of depthmill: `cargo build --release --bin depthmill`; the
  script runs that itself if target/release/depthmill is missing.

image-to-gcode takes its options from a Tk dialog (function ui()).  It is run
without a display by loading /usr/bin/image-to-gcode as a module
(importlib.machinery.SourceFileLoader, with sys.argv = [path, png] so main()
opens the image), replacing `ui` by a function that returns the options dict,
and calling main() with stdout (the G-code) redirected to a file.  It reads
8-bit images only.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

DEBIAN_PYTHON = "/usr/bin/python3"
I2G = "/usr/bin/image-to-gcode"
REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
DEPTHMILL = os.path.join(REPO, "target", "release", "depthmill")

PIXEL_MM = 0.1
DEPTH_MM = 20.0
FIN_TOOL_MM = 3.0
FIN_STEP_PX = 3  # 0.3 mm
ROUGH_TOOL_MM = 6.0
ROUGH_LEAVE_MM = 0.3
ROUGH_STEP_DOWN_MM = 2.0
TOLERANCE_MM = 0.01

try:
    import numpy as np
    from PIL import Image
except ImportError:
    if os.path.realpath(sys.executable) != os.path.realpath(DEBIAN_PYTHON) and os.path.exists(DEBIAN_PYTHON):
        os.execv(DEBIAN_PYTHON, [DEBIAN_PYTHON, os.path.abspath(__file__)] + sys.argv[1:])
    sys.exit("needs numpy and PIL: apt-get install linuxcnc-uspace python3-pil, and run with /usr/bin/python3")


# ---------------------------------------------------------------- the image

def make_image(n, path):
    """Deterministic smooth relief, 8-bit, full 0..255 range."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) / n  # 0..1
    z = np.zeros((n, n))
    for cx, cy, sigma, amp in [
        (0.30, 0.35, 0.12, 1.0),
        (0.70, 0.30, 0.08, 0.7),
        (0.55, 0.72, 0.15, 0.85),
        (0.20, 0.78, 0.06, 0.5),
    ]:
        z += amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
    z += 0.12 * np.sin(2 * np.pi * 5 * x) * np.sin(2 * np.pi * 4 * y + 0.5)
    z = (z - z.min()) / (z.max() - z.min())
    img = np.round(z * 255).astype(np.uint8)
    Image.fromarray(img, mode="L").save(path)
    return img


# ---------------------------------------------------------- image-to-gcode

def i2g_options(tool_type, tool_mm, step_px, roughing_offset, roughing_depth):
    """The full option dict of image-to-gcode's ui() (every key of its `defaults`)."""
    return dict(
        invert=False,
        normalize=False,
        expand=0,  # None
        pixel_size=PIXEL_MM,
        depth=DEPTH_MM,
        pixelstep=step_px,
        tool_diameter=tool_mm,
        safety_height=5.0,
        tool_type=tool_type,  # 0 Ball End, 1 Flat End, 2..4 V
        tolerance=TOLERANCE_MM,
        feed_rate=1000.0,
        plunge_feed_rate=300.0,
        units=1,  # G21 (mm)
        pattern=0,  # Rows
        converter=2,  # Alternating (zigzag)
        bounded=0,
        contact_angle=45,
        spindle_speed=10000,
        roughing_offset=roughing_offset,  # 0 = no roughing
        roughing_depth=roughing_depth,
    )


def i2g_worker(png, options_json, out_path, skip_final_finish):
    """Runs in a child /usr/bin/python3: image-to-gcode's main() with ui() replaced."""
    import contextlib
    import importlib.machinery
    import importlib.util
    import warnings

    warnings.simplefilter("ignore")  # numpy.fromstring deprecation
    options = json.loads(options_json)
    t0 = time.perf_counter()
    sys.argv = [I2G, png]
    loader = importlib.machinery.SourceFileLoader("image_to_gcode", I2G)
    spec = importlib.util.spec_from_loader("image_to_gcode", loader)
    mod = importlib.util.module_from_spec(spec)
    loader.exec_module(mod)
    mod.ui = lambda im, nim, im_name: dict(options)
    skipped = []
    if skip_final_finish:
        one_pass = mod.Converter.one_pass

        def rough_only(self):
            # convert() runs one_pass per roughing level with self.ro = roughing_offset,
            # then sets self.ro = 0 for the final finishing pass: skip only that one.
            if self.roughing_delta and self.roughing_offset and self.ro == 0:
                skipped.append(True)
                return None
            return one_pass(self)

        mod.Converter.one_pass = rough_only
    t1 = time.perf_counter()
    with open(out_path, "w") as f, contextlib.redirect_stdout(f):
        mod.main()
    t2 = time.perf_counter()
    json.dump({"load_s": t1 - t0, "main_s": t2 - t1, "skipped_final_finish": bool(skipped)}, sys.stdout)


def run_i2g(png, out_path, options, skip_final_finish=False):
    cmd = [DEBIAN_PYTHON, os.path.abspath(__file__), "--_i2g-worker", png, json.dumps(options), out_path]
    if skip_final_finish:
        cmd.append("--_skip-final-finish")
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        sys.exit(f"image-to-gcode failed ({p.returncode}):\n{p.stderr[-3000:]}")
    inner = json.loads(p.stdout.strip().splitlines()[-1])
    return {"wall_s": wall, "lines": count_lines(out_path), **inner}


# --------------------------------------------------------------- depthmill

def ensure_depthmill():
    if os.path.exists(DEPTHMILL):
        return
    print(f"{DEPTHMILL} missing: cargo build --release --bin depthmill", flush=True)
    subprocess.run(["cargo", "build", "--release", "--bin", "depthmill"], cwd=REPO, check=True)


def run_depthmill(png, tmp):
    plan = {
        "roughing": {
            "tool": "flat-%g" % ROUGH_TOOL_MM,
            "step_down_mm": ROUGH_STEP_DOWN_MM,
            "stock_to_leave_mm": ROUGH_LEAVE_MM,
            "direction": "x",
        },
        "finishing": {
            "tool": "ball-%g" % FIN_TOOL_MM,
            "strategy": "raster_x",
            "step_over_mm": FIN_STEP_PX * PIXEL_MM,
            "tolerance_mm": TOLERANCE_MM,
        },
    }
    plan_path = os.path.join(tmp, "plan.json")
    with open(plan_path, "w") as f:
        json.dump(plan, f)
    out = os.path.join(tmp, "out.ngc")
    # "--z-min-mm=-20" with "=": clap would take a separate "-20" for a flag.
    cmd = [DEPTHMILL, "plan", png, "--pixel-mm", str(PIXEL_MM), f"--z-min-mm={-DEPTH_MM:g}",
           "--z-max-mm", "0", "--options", plan_path, "-o", out]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        sys.exit(f"depthmill plan failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-3000:]}")
    report_path = os.path.join(tmp, "out.report.json")
    with open(report_path) as f:
        report = json.load(f)
    return {"wall_s": wall, "lines": count_lines(out), "timings_s": report.get("timings_s", {}),
            "stdout": p.stdout.strip(), "report": report}


# ------------------------------------------------------------------- misc

def count_lines(path):
    n = 0
    with open(path, "rb") as f:
        for _ in f:
            n += 1
    return n


def fmt_s(s):
    if s is None:
        return "-"
    return f"{s:9.3f} s" if s < 10 else f"{s:9.2f} s"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=2000, help="image side in pixels (default 2000)")
    ap.add_argument("--skip-roughing", action="store_true", help="do not time image-to-gcode's roughing")
    ap.add_argument("--rough-mode", choices=["skip-finish", "subtract"], default="skip-finish",
                    help="how image-to-gcode's roughing is isolated from its compulsory finishing pass")
    ap.add_argument("--rough-step-px", type=int, default=round(0.4 * ROUGH_TOOL_MM / PIXEL_MM),
                    help="image-to-gcode roughing step-over in pixels (default 24 = 2.4 mm, as depthmill)")
    ap.add_argument("--skip-i2g", action="store_true", help="time depthmill only")
    ap.add_argument("--skip-depthmill", action="store_true", help="time image-to-gcode only")
    ap.add_argument("--keep", action="store_true", help="keep the temp dir")
    ap.add_argument("--_i2g-worker", nargs=3, metavar=("PNG", "OPTIONS", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--_skip-final-finish", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args._i2g_worker:
        i2g_worker(*args._i2g_worker, args._skip_final_finish)
        return

    if not args.skip_i2g and not os.path.exists(I2G):
        sys.exit(f"{I2G} missing: apt-get install linuxcnc-uspace python3-pil")
    if not args.skip_depthmill:
        ensure_depthmill()

    tmp = tempfile.mkdtemp(prefix="depthmill-vs-i2g-")
    png = os.path.join(tmp, f"relief_{args.size}.png")
    img = make_image(args.size, png)
    print(f"image {png}: {args.size} x {args.size}, 8-bit, values {img.min()}..{img.max()}, "
          f"pixel {PIXEL_MM} mm, Z -{DEPTH_MM:g}..0 mm", flush=True)

    rows = []  # (name, seconds, lines)
    i2g_fin = i2g_rough = None
    if not args.skip_i2g:
        print("image-to-gcode finishing (ball 3 mm, step 0.3 mm, rows, zigzag) ...", flush=True)
        fin_opts = i2g_options(0, FIN_TOOL_MM, FIN_STEP_PX, 0.0, ROUGH_STEP_DOWN_MM)
        i2g_fin = run_i2g(png, os.path.join(tmp, "i2g_finish.ngc"), fin_opts)
        print(f"  {i2g_fin['wall_s']:.2f} s wall (main() {i2g_fin['main_s']:.2f} s), {i2g_fin['lines']} lines",
              flush=True)
        rows.append(("image-to-gcode finishing", i2g_fin["wall_s"], i2g_fin["lines"]))
        if not args.skip_roughing:
            rough_opts = i2g_options(1, ROUGH_TOOL_MM, args.rough_step_px, ROUGH_LEAVE_MM, ROUGH_STEP_DOWN_MM)
            print(f"image-to-gcode roughing (flat 6 mm, offset 0.3 mm, step-down 2 mm, "
                  f"step {args.rough_step_px * PIXEL_MM:g} mm, mode {args.rough_mode}) ...", flush=True)
            if args.rough_mode == "skip-finish":
                r = run_i2g(png, os.path.join(tmp, "i2g_rough.ngc"), rough_opts, skip_final_finish=True)
                if not r["skipped_final_finish"]:
                    sys.exit("the final finishing pass was not found to skip: image-to-gcode changed?")
                i2g_rough = dict(r)
                print(f"  {r['wall_s']:.2f} s wall (main() {r['main_s']:.2f} s), {r['lines']} lines "
                      f"(final finishing pass skipped)", flush=True)
            else:
                r = run_i2g(png, os.path.join(tmp, "i2g_rough_finish.ngc"), rough_opts)
                fin6_opts = i2g_options(1, ROUGH_TOOL_MM, args.rough_step_px, 0.0, ROUGH_STEP_DOWN_MM)
                f6 = run_i2g(png, os.path.join(tmp, "i2g_flat6_finish.ngc"), fin6_opts)
                i2g_rough = {"wall_s": r["wall_s"] - f6["wall_s"], "lines": r["lines"] - f6["lines"]}
                print(f"  roughing+finishing {r['wall_s']:.2f} s ({r['lines']} lines) - flat-6 finishing "
                      f"{f6['wall_s']:.2f} s ({f6['lines']} lines) = {i2g_rough['wall_s']:.2f} s", flush=True)
            rows.append(("image-to-gcode roughing", i2g_rough["wall_s"], i2g_rough["lines"]))

    dm = None
    if not args.skip_depthmill:
        print("depthmill plan (flat-6 roughing + ball-3 raster_x finishing + checks, preview) ...", flush=True)
        dm = run_depthmill(png, tmp)
        print(f"  {dm['stdout'].splitlines()[0] if dm['stdout'] else ''}", flush=True)
        rows.append(("depthmill plan (all)", dm["wall_s"], dm["lines"]))

    print()
    print(f"{'tool':<28} {'time':>11} {'blocks':>10}")
    for name, s, n in rows:
        print(f"{name:<28} {fmt_s(s):>11} {n:>10}")
    if dm:
        t = dm["timings_s"]
        if t:
            print("depthmill steps: " + ", ".join(f"{k} {v:.3f} s" for k, v in t.items())
                  + " (roughing, with its tool's compensation, runs beside finishing, with its own)")
    print()
    if dm and i2g_fin:
        if i2g_rough:
            total = i2g_fin["wall_s"] + i2g_rough["wall_s"]
            print(f"(image-to-gcode finishing + roughing) / depthmill total: "
                  f"{total:.2f} s / {dm['wall_s']:.3f} s = {total / dm['wall_s']:.1f}x  (target >= 50x)")
        else:
            print(f"image-to-gcode finishing / depthmill total: {i2g_fin['wall_s']:.2f} s / "
                  f"{dm['wall_s']:.3f} s = {i2g_fin['wall_s'] / dm['wall_s']:.1f}x")
        t = dm["timings_s"]
        if "finishing" in t:
            dm_fin = t["finishing"] + t.get("compensate", 0.0)
            print(f"finishing vs finishing: image-to-gcode {i2g_fin['wall_s']:.2f} s / depthmill "
                  f"finishing (its tool's compensation and passes) {dm_fin:.3f} s = "
                  f"{i2g_fin['wall_s'] / dm_fin:.1f}x")
        if i2g_rough and "roughing" in t:
            print(f"roughing vs roughing: image-to-gcode {i2g_rough['wall_s']:.2f} s / depthmill roughing "
                  f"{t['roughing']:.3f} s = {i2g_rough['wall_s'] / t['roughing']:.1f}x")
    if args.keep:
        print(f"files kept in {tmp}")
    else:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
