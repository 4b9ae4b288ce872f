//! Tool compensation speed: `compensate` on a 2000 x 2000 relief at 0.1 mm, against the brute-force
//! `compensate_reference` measured on a crop in the same run (per-cell cost is independent of the
//! map size, so the crop's time scales linearly). The `Facet` reading's reference is the brute force
//! on the crop's nodes at half the pixel (`facet::facet_nodes`), read at the cells' centres.
//!
//! ```text
//! cargo bench -p depthmill-cam --bench compensate -- [--size 2000] [--repeat 3] [--crop 200]
//! cargo bench -p depthmill-cam --bench compensate -- --map IN.npy --out OUT.npy \
//!     [--tool ball-6] [--model point|column] [--floor Z]
//! ```
//!
//! The second form (used by `scripts/compare_scipy.py`) reads a `.npy` map (sidecar, else 0.1 mm
//! pixels), runs `compensate` once, writes the result and prints `compensate_ms=<ms>` (I/O excluded).

use std::str::FromStr as _;
use std::time::Instant;

use anyhow::{Context as _, bail};
use depthmill_cam::domain::compensate::{
    CompensateOptions, PixelModel, compensate, compensate_reference, kernel,
};
use depthmill_geometry::{HeightMap, HeightMapMeta, ImageMapping, ToolProfile, ToolSpec};
use rayon::prelude::*;

struct Args {
    size: u32,
    repeat: u32,
    crop: u32,
    map: Option<String>,
    out: Option<String>,
    tool: String,
    model: PixelModel,
    floor: Option<f64>,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut a = Args {
        size: 2000,
        repeat: 3,
        crop: 200,
        map: None,
        out: None,
        tool: "ball-6".into(),
        model: PixelModel::Point,
        floor: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        // `cargo bench` passes `--bench` to harness-less benches.
        if flag == "--bench" {
            continue;
        }
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--size" => a.size = value()?.parse().context("--size")?,
            "--repeat" => a.repeat = value()?.parse().context("--repeat")?,
            "--crop" => a.crop = value()?.parse().context("--crop")?,
            "--map" => a.map = Some(value()?),
            "--out" => a.out = Some(value()?),
            "--tool" => a.tool = value()?,
            "--floor" => a.floor = Some(value()?.parse().context("--floor")?),
            "--model" => {
                a.model = match value()?.as_str() {
                    "point" => PixelModel::Point,
                    "column" => PixelModel::Column,
                    "facet" => PixelModel::Facet,
                    other => bail!("--model {other}: expected point, column or facet"),
                }
            }
            other => bail!("unknown argument {other}"),
        }
    }
    Ok(a)
}

fn profile(name: &str) -> anyhow::Result<ToolProfile> {
    let spec = ToolSpec::from_str(name).map_err(|e| anyhow::anyhow!("tool {name}: {e}"))?;
    Ok(spec.profile()?)
}

/// A smooth random relief, 0..~20 mm: seeded Gaussian bumps over a gentle wave (deterministic).
fn relief(w: u32, h: u32, pixel: f64, seed: u64) -> anyhow::Result<HeightMap> {
    let mut state = seed;
    let mut rnd = move || {
        // SplitMix64.
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let bumps: Vec<[f64; 4]> =
        (0..24).map(|_| [rnd(), rnd(), 0.03 + 0.15 * rnd(), 2.0 + 10.0 * rnd()]).collect();
    let (wf, hf) = (f64::from(w), f64::from(h));
    let mut data = vec![0.0f32; w as usize * h as usize];
    data.par_chunks_mut(w as usize).enumerate().for_each(|(r, row)| {
        let y = (r as f64 + 0.5) / hf;
        for (c, z) in row.iter_mut().enumerate() {
            let x = (c as f64 + 0.5) / wf;
            let mut v = 2.0 + 1.5 * (x * 9.0).sin() * (y * 7.0).cos();
            for [bx, by, s, a] in &bumps {
                let d2 = ((x - bx).powi(2) + (y - by).powi(2)) / (s * s);
                if d2 < 30.0 {
                    v += a * (-d2).exp();
                }
            }
            *z = v as f32;
        }
    });
    let mut meta = HeightMapMeta::new(w, h, pixel);
    meta.z_min_mm = 0.0;
    meta.z_max_mm = 25.0;
    Ok(HeightMap::new(meta, data)?)
}

fn crop(map: &HeightMap, n: u32) -> anyhow::Result<HeightMap> {
    let (w, h) = (n.min(map.width()), n.min(map.height()));
    let mut meta = *map.meta();
    meta.width = w;
    meta.height = h;
    let data = (0..h).flat_map(|r| map.row(r).unwrap_or_default()[..w as usize].to_vec()).collect();
    Ok(HeightMap::new(meta, data)?)
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn run_file(a: &Args, input: &str) -> anyhow::Result<()> {
    let out = a.out.as_deref().context("--map needs --out")?;
    let map = depthmill_geometry::read_npy(input, Some(&ImageMapping::pixel_only(0.1)))?;
    let opts = CompensateOptions { pixel_model: a.model, outside_z_mm: a.floor };
    let tool = profile(&a.tool)?;
    let t = Instant::now();
    let c = compensate(&map, &tool, &opts)?;
    let elapsed = ms(t);
    depthmill_geometry::write_npy(&c, out)?;
    println!(
        "map {}x{} at {} mm, tool {}, model {:?}",
        map.width(),
        map.height(),
        map.pixel_mm(),
        a.tool,
        a.model
    );
    println!("compensate_ms={elapsed:.3}");
    Ok(())
}

fn run_bench(a: &Args) -> anyhow::Result<()> {
    let t = Instant::now();
    let map = relief(a.size, a.size, 0.1, 42)?;
    println!(
        "relief {0}x{0} at 0.1 mm built in {1:.0} ms; {2} rayon threads",
        a.size,
        ms(t),
        rayon::current_num_threads()
    );
    let mpx = f64::from(a.size) * f64::from(a.size) / 1e6;
    let small = crop(&map, a.crop)?;
    for (name, model) in [
        ("ball-6", PixelModel::Point),
        ("ball-6", PixelModel::Column),
        ("ball-6", PixelModel::Facet),
        ("flat-6", PixelModel::Column),
        ("bull-6-1", PixelModel::Column),
    ] {
        let tool = profile(name)?;
        let opts = CompensateOptions { pixel_model: model, outside_z_mm: None };
        let mut best = f64::INFINITY;
        for _ in 0..a.repeat.max(1) {
            let t = Instant::now();
            let c = compensate(&map, &tool, &opts)?;
            best = best.min(ms(t));
            std::hint::black_box(c);
        }
        // Facet: the reference dilates the crop's nodes at half the pixel and reads the centres.
        let nodes = match model {
            PixelModel::Facet => Some(depthmill_geometry::facet::facet_nodes(
                &small,
                depthmill_geometry::facet::FACET_STEEP_SLOPE,
            )?),
            _ => None,
        };
        let k = match model {
            PixelModel::Facet => kernel(&tool, 0.05, PixelModel::Point),
            _ => kernel(&tool, 0.1, model),
        };
        let cells: usize = k.rows.iter().map(|r| r.heights.len()).sum();
        let t = Instant::now();
        let slow = match &nodes {
            Some(n) => {
                let fine = compensate_reference(n, &k, small.z_min_mm() as f32);
                let fw = n.width() as usize;
                let w = small.width() as usize;
                (0..small.height() as usize)
                    .flat_map(|j| (0..w).map(move |i| (j, i)))
                    .map(|(j, i)| fine[(2 * j + 1) * fw + 2 * i + 1])
                    .collect()
            }
            None => compensate_reference(&small, &k, small.z_min_mm() as f32),
        };
        let ref_ms = ms(t) * (mpx * 1e6) / small.data().len() as f64;
        let fast_small = compensate(&small, &tool, &opts)?;
        let diff = fast_small.data().iter().zip(&slow).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        std::hint::black_box(slow);
        println!(
            "{name:9} {model:?}: {cells} kernel cells; compensate {best:.1} ms ({:.1} Mpixel/s); \
             reference ~{ref_ms:.0} ms (extrapolated from {cw}x{cw}); speed-up x{:.0}; max |diff| {diff:e}",
            mpx / (best / 1e3),
            ref_ms / best,
            cw = small.width(),
        );
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let a = parse_args()?;
    match a.map.clone() {
        Some(input) => run_file(&a, &input),
        None => run_bench(&a),
    }
}
