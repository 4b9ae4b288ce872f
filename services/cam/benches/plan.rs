//! Full plan time: roughing + compensation + finishing + holder check + clean-up + preview +
//! G-code, on synthetic reliefs of 1000 x 1000 and 2000 x 2000 cells at 0.1 mm.
//!
//! ```text
//! cargo bench -p depthmill-cam --bench plan -- [--sizes 1000,2000] [--step-over 0.3]
//! ```
//!
//! Prints the wall time of each step (from the plan report) and the program size.

use anyhow::Context as _;
use depthmill_cam::domain::feeds::MachineLimits;
use depthmill_cam::domain::plan::{FaceInput, FinishingOptions, PlanOptions, RoughingOptions, plan};
use depthmill_cam::domain::tool::ToolLibrary;
use depthmill_geometry::{HeightMap, HeightMapMeta};

/// A smooth relief of a few bumps and a ridge, 0..20 mm, deterministic.
fn relief(n: u32, pixel: f64) -> anyhow::Result<HeightMap> {
    let mut meta = HeightMapMeta::new(n, n, pixel);
    meta.z_min_mm = 0.0;
    meta.z_max_mm = 25.0;
    let bumps =
        [(0.3, 0.3, 0.18, 12.0), (0.7, 0.4, 0.12, 8.0), (0.5, 0.75, 0.2, 15.0), (0.2, 0.8, 0.08, 6.0)];
    Ok(HeightMap::from_fn(meta, |c, r| {
        let (x, y) = ((f64::from(c) + 0.5) / f64::from(n), (f64::from(r) + 0.5) / f64::from(n));
        let mut z = 2.0 + 1.5 * (x * 9.0).sin() * (y * 7.0).cos();
        for (bx, by, w, h) in bumps {
            let d2 = ((x - bx).powi(2) + (y - by).powi(2)) / (w * w);
            z += h * (-d2).exp();
        }
        let ridge = (y - 0.5 - 0.1 * (x * 12.0).sin()).abs();
        if ridge < 0.02 {
            z += 4.0;
        }
        z.clamp(0.0, 25.0) as f32
    })?)
}

fn main() -> anyhow::Result<()> {
    let mut sizes = vec![1000u32, 2000];
    let mut step_over = 0.3;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--sizes" => {
                sizes = args
                    .next()
                    .context("--sizes needs a list")?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?;
            }
            "--step-over" => step_over = args.next().context("--step-over needs a value")?.parse()?,
            "--bench" => {}
            other => anyhow::bail!("unknown argument {other}"),
        }
    }
    let library = ToolLibrary::builtin()?;
    let options = PlanOptions {
        roughing: Some(RoughingOptions {
            tool: Some("flat-6".into()),
            step_down_mm: Some(2.0),
            stock_to_leave_mm: Some(0.3),
            direction: Some("x".into()),
        }),
        finishing: Some(FinishingOptions {
            tool: Some("ball-3".into()),
            strategy: Some("raster_x".into()),
            step_over_mm: Some(step_over),
            tolerance_mm: Some(0.01),
            arcs: Some(true),
            ..Default::default()
        }),
        ..Default::default()
    };
    println!("threads {}", rayon::current_num_threads());
    for n in sizes {
        let map = relief(n, 0.1)?;
        let started = std::time::Instant::now();
        let out = plan(
            &[FaceInput { a_deg: None, map, roughing_map: None }],
            &options,
            &library,
            &MachineLimits::emco_f1(),
            &|_, _| {},
            &|| false,
        )?;
        let total = started.elapsed().as_secs_f64();
        let steps: Vec<String> = out.report.timings_s.iter().map(|(k, v)| format!("{k} {v:.2} s")).collect();
        println!(
            "{n}x{n} @0.1 mm: total {total:.2} s  [{}]  blocks {}  program {:.1} MB  est. machining {:.0} min  gouge {:.4} mm",
            steps.join(", "),
            out.report.blocks,
            out.gcode.len() as f64 / 1e6,
            out.report.estimated_time_s / 60.0,
            out.preview.max_gouge_mm
        );
    }
    Ok(())
}
