//! Offsetting 10 000 contours with the two pure-Rust offsetters considered: clipper2-rust (a
//! port of Clipper2) and i_overlay (the engine of geo's `buffer`).
//! `cargo bench -p depthmill-cam --bench offset`.
//!
//! The contours: 10 000 star-shaped polygons of 64 vertices (radius 2-6 mm, a wavy rim), on a
//! grid 12 mm apart (the largest merge when grown by 1 mm). Each engine offsets them outward by
//! 1 mm and inward by 0.5 mm with round joins at 0.01 mm arc tolerance: all in one call (once),
//! and each contour in a call of its own (best of 3). Printed: times, contours, areas, and the
//! largest error of the result's distance from the input (every 50th contour's vertices).

use std::f64::consts::TAU;
use std::time::Instant;

use clipper2_rust::{EndType, JoinType, PointD, inflate_paths_d};
use i_overlay::mesh::float::outline::offset::OutlineOffset;
use i_overlay::mesh::float::style::{LineJoin, OutlineStyle};

const ARC_TOL: f64 = 0.01;

fn stars(n: usize) -> Vec<Vec<[f64; 2]>> {
    let side = (n as f64).sqrt().ceil() as usize;
    (0..n)
        .map(|k| {
            let (cx, cy) = ((k % side) as f64 * 12.0, (k / side) as f64 * 12.0);
            let r0 = 2.0 + 3.0 * ((k * 7919) % 1000) as f64 / 1000.0;
            let lobes = 3 + k % 6;
            (0..64)
                .map(|i| {
                    let a = TAU * i as f64 / 64.0;
                    let r = r0 * (1.0 + 0.2 * (lobes as f64 * a).sin());
                    [cx + r * a.cos(), cy + r * a.sin()]
                })
                .collect()
        })
        .collect()
}

fn area(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    0.5 * (0..n).map(|i| p[i][0] * p[(i + 1) % n][1] - p[(i + 1) % n][0] * p[i][1]).sum::<f64>()
}

fn clipper(contours: &[Vec<[f64; 2]>], delta: f64) -> Vec<Vec<[f64; 2]>> {
    let paths: Vec<Vec<PointD>> =
        contours.iter().map(|c| c.iter().map(|p| PointD::new(p[0], p[1])).collect()).collect();
    inflate_paths_d(&paths, delta, JoinType::Round, EndType::Polygon, 2.0, 6, ARC_TOL)
        .into_iter()
        .map(|c| c.into_iter().map(|p| [p.x, p.y]).collect())
        .collect()
}

fn overlay(contours: &[Vec<[f64; 2]>], delta: f64) -> Vec<Vec<[f64; 2]>> {
    // Round join step: the chord angle whose sagitta is the arc tolerance.
    let angle = 2.0 * (1.0 - ARC_TOL / delta.abs()).acos();
    let style = OutlineStyle::new(delta).line_join(LineJoin::Round(angle));
    // One shape per contour (no holes here).
    let shapes: Vec<Vec<Vec<[f64; 2]>>> = contours.iter().map(|c| vec![c.clone()]).collect();
    shapes.outline(&style).into_iter().flatten().collect()
}

fn dist_to_polygon(p: [f64; 2], poly: &[[f64; 2]]) -> f64 {
    let n = poly.len();
    (0..n)
        .map(|i| {
            let (a, b) = (poly[i], poly[(i + 1) % n]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let t = (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / (dx * dx + dy * dy)).clamp(0.0, 1.0);
            (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
        })
        .fold(f64::INFINITY, f64::min)
}

/// Largest |distance to the input - |delta|| over every vertex of every 50th result contour.
fn worst_distance(input: &[Vec<[f64; 2]>], out: &[Vec<[f64; 2]>], delta: f64) -> f64 {
    let boxes: Vec<([f64; 2], [f64; 2])> = input
        .iter()
        .map(|q| {
            q.iter().fold(([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]), |(lo, hi), v| {
                ([lo[0].min(v[0]), lo[1].min(v[1])], [hi[0].max(v[0]), hi[1].max(v[1])])
            })
        })
        .collect();
    let r = delta.abs() + 1.0;
    out.iter()
        .step_by(50)
        .flat_map(|c| c.iter())
        .map(|&p| {
            // Only the inputs whose box is within reach (the stars are 12 mm apart).
            let d = input
                .iter()
                .zip(&boxes)
                .filter(|(_, (lo, hi))| {
                    p[0] > lo[0] - r && p[0] < hi[0] + r && p[1] > lo[1] - r && p[1] < hi[1] + r
                })
                .map(|(q, _)| dist_to_polygon(p, q))
                .fold(f64::INFINITY, f64::min);
            (d - delta.abs()).abs()
        })
        .fold(0.0, f64::max)
}

fn main() {
    let input = stars(10_000);
    let points: usize = input.iter().map(Vec::len).sum();
    println!(
        "offsetting benchmark: {} contours, {points} points, round joins, arc tolerance {ARC_TOL} mm",
        input.len()
    );
    let a_in: f64 = input.iter().map(|c| area(c)).sum();
    type Engine = fn(&[Vec<[f64; 2]>], f64) -> Vec<Vec<[f64; 2]>>;
    let engines: [(&str, Engine); 2] = [("clipper2-rust", clipper), ("i_overlay", overlay)];
    for delta in [1.0, -0.5] {
        println!("offset {delta:+} mm (input area {a_in:.1} mm2):");
        let mut times = Vec::new();
        for (name, f) in engines {
            // All contours in one call (overlapping results merge), once; then each contour in a
            // call of its own (a layer's few contours at a time), best of 3.
            let t = Instant::now();
            let out = f(&input, delta);
            let whole = t.elapsed().as_secs_f64();
            let mut each = f64::INFINITY;
            let mut singles = Vec::new();
            for _ in 0..3 {
                let t = Instant::now();
                singles = input.iter().flat_map(|c| f(std::slice::from_ref(c), delta)).collect::<Vec<_>>();
                each = each.min(t.elapsed().as_secs_f64());
            }
            let a: f64 = out.iter().map(|c| area(c)).sum();
            let a1: f64 = singles.iter().map(|c| area(c)).sum();
            println!(
                "  {name:14} one call {whole:7.3} s: {} contours, area {a:.2} mm2, worst distance error {:.2e} mm",
                out.len(),
                worst_distance(&input, &out, delta)
            );
            println!(
                "  {name:14} per contour {each:7.3} s (best of 3): {} contours, area {a1:.2} mm2, worst distance error {:.2e} mm",
                singles.len(),
                worst_distance(&input, &singles, delta)
            );
            times.push((whole, each));
        }
        println!(
            "  i_overlay vs clipper2-rust: {:.1}x faster in one call, {:.1}x per contour",
            times[0].0 / times[1].0,
            times[0].1 / times[1].1
        );
    }
}
