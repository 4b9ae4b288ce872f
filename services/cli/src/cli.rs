//! The `depthmill` command line: the embedded stack (`serve`), the client verbs (`submit`,
//! `status`, `watch`, `fetch`) and the offline tools. The binary is [`main_from`] on the process's
//! arguments; tests run it in processes of their own.

use crate::{cam, client, demo, machine, raster, robot, scan, slice, token};

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context as _;
use clap::{Parser, Subcommand};

/// depthmill: from a scanned part to a machined copy.
///
/// `depthmill serve` runs every service in one process (the embedded default: SQLite file and
/// artifact folder in --data-dir). The client verbs talk to a running orchestrator's REST API
/// (--url, or DEPTHMILL_URL; default http://127.0.0.1:8080).
#[derive(Parser)]
#[command(version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log as JSON lines.
    #[arg(long, global = true)]
    log_json: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Run the orchestrator and every stage service in this process.
    ///
    /// The stage services listen on loopback ports chosen by the system and the orchestrator
    /// reaches them over gRPC, as it would across machines. Prints `REST listening on
    /// http://HOST:PORT` once it accepts requests.
    Serve {
        /// Holds artifacts/, node_id and (without --database-url) jobs.sqlite.
        #[arg(long, default_value = "data")]
        data_dir: PathBuf,
        /// Job database: sqlite://PATH or postgres://USER@HOST:PORT/DB (several replicas share
        /// one PostgreSQL database). Default: sqlite://DATA_DIR/jobs.sqlite.
        #[arg(long, env = "DEPTHMILL_DATABASE_URL")]
        database_url: Option<String>,
        /// REST address; port 0 picks a free port.
        #[arg(long, default_value = "127.0.0.1:8080")]
        rest_addr: SocketAddr,
        /// Orchestrator gRPC address; port 0 picks a free port.
        #[arg(long, default_value = "127.0.0.1:50050")]
        grpc_addr: SocketAddr,
        /// Orchestrator configuration (TOML, see deploy/config/orchestrator.toml); the flags above win.
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Upload a local file and submit a job that starts from it; prints the job id.
    ///
    /// The input kind follows the extension (.stl mesh; .xyz/.ply point cloud; .png/.npy depth map;
    /// .ngc/.nc/.gcode/.tap G-code) unless --kind says otherwise.
    Submit {
        file: PathBuf,
        /// mesh, point_cloud, depth_map or gcode.
        #[arg(long)]
        kind: Option<String>,
        /// A job request JSON (DESIGN.md §7) whose sections (scan, reconstruct, plan, execute, name)
        /// are used; its input is replaced by the uploaded file.
        #[arg(long)]
        options: Option<PathBuf>,
        #[arg(long)]
        name: Option<String>,
        /// Pixel size of a depth image without depthmill metadata.
        #[arg(long)]
        pixel_mm: Option<f64>,
        #[arg(long, allow_negative_numbers = true)]
        z_min_mm: Option<f64>,
        #[arg(long, allow_negative_numbers = true)]
        z_max_mm: Option<f64>,
        /// Length unit of a mesh or point cloud: auto (default; the header, else metres under 2
        /// units across, else mm), mm, m or in.
        #[arg(long)]
        units: Option<String>,
        /// Repeat-safe submission: the same key returns the same job.
        #[arg(long)]
        idempotency_key: Option<String>,
        /// Make the part by robot milling from the mesh (`"process": "robot"`; settings in the
        /// options file's `robot` section).
        #[arg(long)]
        robot: bool,
        #[command(flatten)]
        server: client::Server,
    },
    /// Print a job's status (as JSON with --json).
    Status {
        id: String,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        server: client::Server,
    },
    /// Show a live progress bar until the job ends; exits non-zero unless it succeeded.
    Watch {
        id: String,
        #[command(flatten)]
        server: client::Server,
    },
    /// Compensate a depth map for a tool: the surface the tool tip follows (no server).
    Compensate {
        /// Depth map: .png (depthmill metadata, or give --pixel-mm and the Z range) or .npy.
        map: PathBuf,
        /// Tool: a name (ball-6, flat-6, bull-6-1, v-6-90, or one of the shipped library) or a .tool file.
        #[arg(long)]
        tool: String,
        /// Pixel reading: column (conservative: each cell a square column), point (cell-centre samples)
        /// or facet (a piecewise-linear surface through the centres standing above their convex edges).
        #[arg(long, default_value = "column")]
        model: String,
        /// Height of everything outside the map and of cells without data (default: the map's z_min).
        #[arg(long, allow_negative_numbers = true)]
        floor_mm: Option<f64>,
        #[command(flatten)]
        map_args: cam::MapArgs,
        /// Extra folder of .tool files.
        #[arg(long)]
        tools_dir: Option<PathBuf>,
        /// Output: .npy (f32 mm) or .png (16-bit with metadata).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Plan roughing and finishing for a depth map and write the G-code (no server).
    ///
    /// Also writes <stem>.report.json, <stem>.preview.png (the surface the program leaves) and
    /// <stem>.leftover.png next to the program.
    ///
    /// With --robot, MAP is a mesh (STL/OBJ/OFF/PLY) milled layer by layer by the 6-axis arm with a
    /// spindle: writes the Cartesian program (tool tip X Y Z, tool axis A B), <stem>.joints.json
    /// (the joint trajectory) and <stem>.robot.json (clearance, tilts, reach, timing).
    Plan {
        map: PathBuf,
        /// The job's "plan" object as JSON (stock, roughing, finishing, dialect), as in DESIGN.md §7.
        #[arg(long)]
        options: Option<PathBuf>,
        /// Over-approximating map for roughing.
        #[arg(long)]
        roughing_map: Option<PathBuf>,
        #[command(flatten)]
        map_args: cam::MapArgs,
        #[arg(long)]
        tools_dir: Option<PathBuf>,
        #[command(flatten)]
        robot: robot::RobotArgs,
        /// Output program (.ngc).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Rasterise a point cloud (XYZ/PCD/PLY) or mesh (STL/OBJ/OFF/PLY) into depth maps (no server).
    ///
    /// Writes OUTPUT (.png or .npy), <stem>.coverage.png, <stem>.roughing.<ext> and
    /// <stem>.report.json; several --face flags give one map per face (<stem>.face1.<ext>, ...).
    Raster {
        input: PathBuf,
        #[command(flatten)]
        args: raster::RasterArgs,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Slice a mesh (STL/OBJ/OFF/PLY) into planar layers (no server).
    ///
    /// Writes OUTPUT (JSON): the mesh's edge check (open, non-manifold and misoriented edges)
    /// and every layer's closed contours (counter-clockwise outer boundaries, clockwise holes,
    /// their nesting), open chains and defects.
    Slice {
        mesh: PathBuf,
        #[command(flatten)]
        args: slice::SliceArgs,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// The whole product on the sample part: starts the embedded stack, scans, reconstructs,
    /// plans, machines and reports, then writes everything to OUTPUT.
    Demo {
        #[command(flatten)]
        args: demo::DemoArgs,
    },
    /// Scan a part's mesh (STL/OBJ/OFF/PLY) on the simulated cell into a point cloud (no server).
    ///
    /// Writes OUTPUT (binary PLY: x y z, intensity, pass id, in the mesh's frame) and
    /// <stem>.scan.json (plan, passes, drops, registration error, coverage).
    Scan {
        mesh: PathBuf,
        #[command(flatten)]
        args: scan::ScanArgs,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Interpret and validate a program without cutting (no server): blocks, moves, extents,
    /// travel, feeds and speeds, estimated cycle time; errors name the line and column.
    Check {
        program: PathBuf,
        #[command(flatten)]
        args: machine::MachineArgs,
    },
    /// Run a program on the simulated mill (no server): final stock, telemetry CSV and plot,
    /// deviation from a target depth map, report.json, in OUTDIR.
    Simulate {
        program: PathBuf,
        #[command(flatten)]
        args: machine::SimulateArgs,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Create, list and revoke API tokens (on the job database, not through the API).
    Token {
        #[command(subcommand)]
        command: token::TokenCommand,
    },
    /// Download a job's artifacts and its JSON into a folder.
    Fetch {
        id: String,
        #[arg(short, long, default_value = ".")]
        output: PathBuf,
        #[command(flatten)]
        server: client::Server,
    },
}

/// Runs the command line `args` (the program name first); the process's exit code: 0, or 1 after
/// one line on standard error saying what failed and why (the causes joined: a server that is
/// down, a reply that is not what the API sends, a file that cannot be read). Bad arguments are
/// clap's: usage on standard error and exit code 2.
pub fn main_from<I, T>(args: I) -> u8
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = Cli::parse_from(args);
    match run(cli) {
        Ok(()) => 0,
        Err(e) => {
            use std::io::Write as _;
            let _ = writeln!(std::io::stderr(), "depthmill: {e:#}");
            1
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let runtime =
        tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the runtime")?;
    runtime.block_on(async move {
        match cli.command {
            Command::Serve { data_dir, database_url, rest_addr, grpc_addr, config } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                crate::embedded::serve(data_dir, database_url, rest_addr, grpc_addr, config).await
            }
            Command::Submit {
                file,
                kind,
                options,
                name,
                pixel_mm,
                z_min_mm,
                z_max_mm,
                units,
                idempotency_key,
                robot,
                server,
            } => {
                let submit = client::Submit {
                    file,
                    kind,
                    options,
                    name,
                    pixel_mm,
                    z_min_mm,
                    z_max_mm,
                    units,
                    idempotency_key,
                    robot,
                };
                let id = client::submit(&server, submit).await?;
                crate::outln!("{id}");
                Ok(())
            }
            Command::Status { id, json, server } => client::status(&server, &id, json).await,
            Command::Watch { id, server } => client::watch(&server, &id).await,
            Command::Fetch { id, output, server } => client::fetch(&server, &id, &output).await,
            Command::Token { command } => token::run(command).await,
            Command::Compensate { map, tool, model, floor_mm, map_args, tools_dir, output } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                tokio::task::block_in_place(|| {
                    cam::run_compensate(
                        &map,
                        &tool,
                        &model,
                        floor_mm,
                        &map_args,
                        tools_dir.as_deref(),
                        &output,
                    )
                })
            }
            Command::Check { program, args } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                tokio::task::block_in_place(|| machine::run_check(&program, &args))
            }
            Command::Simulate { program, args, output } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                tokio::task::block_in_place(|| machine::run_simulate(&program, &args, &output))
            }
            Command::Demo { args } => {
                depthmill_common::telemetry::init_tracing_with_default(cli.log_json, "warn");
                demo::run(&args).await
            }
            Command::Scan { mesh, args, output } => {
                depthmill_common::telemetry::init_tracing_with_default(cli.log_json, "warn");
                scan::run(&mesh, &args, &output).await
            }
            Command::Slice { mesh, args, output } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                tokio::task::block_in_place(|| slice::run(&mesh, &args, &output))
            }
            Command::Raster { input, args, output } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                tokio::task::block_in_place(|| raster::run(&input, &args, &output))
            }
            Command::Plan { map, options, roughing_map, map_args, tools_dir, robot, output } => {
                depthmill_common::telemetry::init_tracing(cli.log_json);
                if robot.robot {
                    if options.is_some() || roughing_map.is_some() {
                        anyhow::bail!(
                            "--robot plans from the mesh alone: --options and --roughing-map do not apply"
                        );
                    }
                    return tokio::task::block_in_place(|| {
                        robot::run(&map, &robot, tools_dir.as_deref(), &output)
                    });
                }
                tokio::task::block_in_place(|| {
                    cam::run_plan(
                        &map,
                        options.as_deref(),
                        roughing_map.as_deref(),
                        &map_args,
                        tools_dir.as_deref(),
                        &output,
                    )
                })
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use clap::Parser as _;

    use super::*;

    #[test]
    fn negative_values_and_faces_parse_as_values() {
        let cli = Cli::try_parse_from([
            "depthmill",
            "raster",
            "in.ply",
            "--face",
            "-Z",
            "--units",
            "m",
            "-o",
            "x.png",
        ])
        .expect("raster with -Z");
        let Command::Raster { args, .. } = cli.command else { panic!("not raster") };
        assert_eq!((args.face, args.units.as_deref()), (vec!["-Z".to_string()], Some("m")));
        let cli = Cli::try_parse_from([
            "depthmill",
            "submit",
            "d.png",
            "--z-min-mm",
            "-745",
            "--z-max-mm",
            "-700.5",
        ])
        .expect("submit with negative Z");
        let Command::Submit { z_min_mm, z_max_mm, .. } = cli.command else { panic!("not submit") };
        assert_eq!((z_min_mm, z_max_mm), (Some(-745.0), Some(-700.5)));
        let cli = Cli::try_parse_from([
            "depthmill",
            "compensate",
            "m.png",
            "--tool",
            "ball-6",
            "--floor-mm",
            "-3",
            "-o",
            "t.npy",
        ])
        .expect("compensate with a negative floor");
        let Command::Compensate { floor_mm, .. } = cli.command else { panic!("not compensate") };
        assert_eq!(floor_mm, Some(-3.0));
    }
}
