//! The whole robot plan of the demo part (`cargo bench -p depthmill-cam --bench robot`).
//!
//! The part: the generated sample relief of `depthmill demo` (80 x 60 mm, sampled every 0.5 mm),
//! 420 mm in front of the Viper s650's base; a flat-6 in its default holder on a 150 mm x 60 mm
//! spindle; layers every 1 mm. Prints the best of 3 of each stage of [`plan_robot`] (slicing and
//! rings, the clearance check with tilting, the arm's joint trajectory) and, as the baseline
//! measured in the same run, the upright clearance check of every position with the grid's
//! candidates against the same check testing every triangle.

use std::time::Instant;

use depthmill_cam::domain::clearance::{
    MeshIndex, Scratch, TiltOptions, ToolBody, any_axis, clear_path, collides, never,
};
use depthmill_cam::domain::layer_passes::{MeshProgramOptions, MoveKind, mesh_program};
use depthmill_cam::domain::robot::{RobotCell, RobotJob, plan_robot, robot_program};
use depthmill_cam::domain::tool::Tool;
use depthmill_geometry::nalgebra::{Isometry3, Point3, Vector3};
use depthmill_geometry::sample::sample_relief;

fn best<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut out = None;
    let mut best = f64::INFINITY;
    for _ in 0..runs {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("at least one run"))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mesh = sample_relief(0.5);
    let tool = Tool::from_spec(&"flat-6".parse()?)?;
    let job = RobotJob {
        auto_place: false,
        layers: MeshProgramOptions::new(1.0, tool.radius_mm()),
        tilt: TiltOptions::default(),
        cell: RobotCell::viper_s650(Isometry3::translation(420.0, 0.0, 0.0)),
        feed_mm_min: 600.0,
        tool: tool.clone(),
    };
    println!("demo part: {} triangles", mesh.triangles.len());
    let (t_all, plan) = best(3, || plan_robot(&mesh, &job));
    let plan = plan?;
    let (t_layers, layers) = best(3, || mesh_program(&mesh, &job.layers));
    let layers = layers?;
    let index = MeshIndex::new(&mesh);
    let body = ToolBody::new(&tool, job.tilt.gouge_tol_mm, Some((60.0, 150.0)));
    let moves: Vec<([f64; 3], bool)> =
        layers.program.moves.iter().map(|m| (m.to, m.kind == MoveKind::Rapid)).collect();
    let start = [moves[0].0[0], moves[0].0[1], layers.clear_z_mm];
    let (t_clear, _) = best(3, || clear_path(&index, &body, start, &moves, &job.tilt, &any_axis, &never));
    let (t_arm, _) = best(3, || robot_program(&job.cell, &tool, &plan.path, job.feed_mm_min, None));
    let c = &plan.path;
    println!(
        "plan: {} layers, {} positions ({} collide upright, {} tilted, max {:.1}°, {} blocked); arm {:.1} min, {} unreachable stretches",
        layers.layers.len(),
        c.points.len(),
        c.colliding,
        c.tilted,
        c.max_tilt_deg,
        c.blocked.len(),
        plan.robot.duration_s / 60.0,
        plan.robot.unreachable.len()
    );
    println!(
        "whole robot plan {:.3} s: layers {:.3} s, clearance and tilting {:.3} s, joint trajectory {:.3} s",
        t_all, t_layers, t_clear, t_arm
    );
    // Baseline: the upright check of every position, grid vs every triangle.
    let all = MeshIndex::unindexed(&mesh);
    let upright = |ix: &MeshIndex| {
        let mut s = Scratch::default();
        c.points
            .iter()
            .filter(|p| collides(ix, &body, &Point3::from(p.tip), &Vector3::z_axis(), &mut s))
            .count()
    };
    let (t_grid, n_grid) = best(3, || upright(&index));
    let (t_brute, n_brute) = best(1, || upright(&all));
    assert_eq!(n_grid, n_brute, "the grid and the every-triangle check disagree");
    println!(
        "upright check of {} positions: grid {:.4} s, every triangle {:.3} s: x{:.0}",
        c.points.len(),
        t_grid,
        t_brute,
        t_brute / t_grid
    );
    Ok(())
}
