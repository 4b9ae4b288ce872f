//! `depthmill scan`: a mesh scanned on the simulated cell into a point cloud, on local files.
//!
//! The cell is the scanning service's: the arm, latch and scanner simulated in-process, the rotary
//! table a simulated controller on a loopback socket driven over its ASCII protocol, exactly as
//! the service does.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context as _, bail};
use depthmill_geometry::formats::{ReadLimits, read_mesh};
use depthmill_scanning::devices::table::{SimulatedTable, TableClient};
use depthmill_scanning::domain::calibration::{CalibrationOptions, Cell, CellErrors};
use depthmill_scanning::domain::scan::{CellLayout, ScanOptions};
use depthmill_scanning::domain::table::TableConfig;

/// Options of `depthmill scan` besides the input and output.
#[derive(clap::Args, Debug, Clone)]
pub struct ScanArgs {
    /// The job's `scan` object as a JSON file (mode, table_angles_deg, standoff_mm, line_rate_hz,
    /// adaptive_rescan, line_spacing_mm, ...; README "Scan options").
    #[arg(long)]
    pub options: Option<PathBuf>,
    /// Also write the scan report (JSON) here (default: <output stem>.scan.json).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Scan on the mill instead of the robot cell: an area scanner in the EMCO's tool holder, the
    /// part on its A axis (the mesh's X along the axis), the scanner calibrated against the
    /// machine's axes first and every shot placed by the kinematic chain alone (no markers, no
    /// overlap). `--options` is then the machine scan's JSON (a_angles_deg, standoff_mm,
    /// overlap, seed).
    #[arg(long)]
    pub on_machine: bool,
}

/// Reads the options file; errors name the file and the field.
pub fn load_options(path: Option<&Path>) -> anyhow::Result<ScanOptions> {
    let Some(path) = path else {
        return Ok(ScanOptions::default());
    };
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    ScanOptions::from_json(&text).with_context(|| format!("{}", path.display()))
}

pub async fn run(input: &Path, args: &ScanArgs, output: &Path) -> anyhow::Result<()> {
    if output.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() != Some("ply") {
        bail!("{}: the scan is written as PLY; give an output ending in .ply", output.display());
    }
    if args.on_machine {
        let (input, args, output) = (input.to_path_buf(), args.clone(), output.to_path_buf());
        return tokio::task::spawn_blocking(move || run_on_machine(&input, &args, &output)).await?;
    }
    let opts = load_options(args.options.as_deref())?;
    let path = input.to_path_buf();
    let (mesh, _) = tokio::task::spawn_blocking(move || read_mesh(&path, &ReadLimits::default()))
        .await
        .context("reading the mesh")??;
    // The table's controller on a loopback socket, driven over its protocol.
    let listener =
        tokio::net::TcpListener::bind(("127.0.0.1", 0)).await.context("binding the table's socket")?;
    let addr = listener.local_addr()?;
    let stop = tokio_util::sync::CancellationToken::new();
    let sim = SimulatedTable::new(TableConfig::default()).map_err(|e| anyhow::anyhow!("{e}"))?;
    let server = tokio::spawn(sim.serve(listener, stop.clone().cancelled_owned()));
    let mut table = TableClient::connect(addr).await.context("connecting to the table")?;
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent:>3}% {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let b = bar.clone();
    let progress: depthmill_scanning::session::Progress = Arc::new(move |f, m| {
        b.set_position((f * 1000.0) as u64);
        b.set_message(m);
    });
    let started = std::time::Instant::now();
    // The simulated cell is off its drawing as a real one is: the scan calibrates it (at its own
    // stations when the part leaves the reference sphere's nest free, else first).
    let layout = CellLayout::default();
    let errors = CellErrors::default();
    let result = depthmill_scanning::session::run_scan(
        mesh,
        opts,
        layout,
        Cell::new(&layout, &errors, None),
        Some(CalibrationOptions::default()),
        &mut table,
        progress,
        tokio_util::sync::CancellationToken::new(),
    )
    .await
    .context("scanning");
    if let Ok((_, Some(made))) = &result
        && let (Some(b), Some(a)) = (made.report.registration_before, made.report.registration_after)
    {
        bar.println(format!(
            "cell calibrated {}: merge error {:.4} mm before, {:.4} mm after",
            match &made.why_not {
                None => "at the scan's stations".to_string(),
                Some(why) => format!("before the scan ({why})"),
            },
            b.merge_rms_mm,
            a.merge_rms_mm
        ));
    }
    let result = result.map(|(out, _)| out);
    bar.finish_and_clear();
    drop(table);
    stop.cancel();
    let _ = server.await;
    let out = result.with_context(|| format!("{}", input.display()))?;
    let (out, bytes) = tokio::task::spawn_blocking(move || {
        let b = depthmill_scanning::encode_cloud(&out);
        (out, b)
    })
    .await?;
    let bytes = bytes?;
    std::fs::write(output, &bytes).with_context(|| format!("writing {}", output.display()))?;
    let report_path = args.report.clone().unwrap_or_else(|| output.with_extension("scan.json"));
    std::fs::write(&report_path, serde_json::to_vec_pretty(&out.report)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    let r = &out.report;
    crate::outln!(
        "{}: {} points from {} frames in {} passes at {} table angles; simulated scan time {:.1} s, wall {:.1} s",
        output.display(),
        r.points,
        r.frames,
        r.stations.iter().map(|s| s.passes.len()).sum::<usize>(),
        r.stations.len(),
        r.scan_time_s,
        started.elapsed().as_secs_f64()
    );
    crate::outln!(
        "registration error RMS {:.4} mm (max {:.4}); dropped rays: {} out of window, {} incidence, {} occluded, {} missed",
        r.registration_rms_mm,
        r.registration_max_mm,
        r.dropped.out_of_window,
        r.dropped.incidence,
        r.dropped.occluded,
        r.dropped.miss
    );
    if let Some(b) = r.coverage_before_rescan {
        crate::out!("coverage {:.2} % ({} holes)", b.covered_pct, b.holes);
        if let Some(a) = r.coverage_after_rescan {
            crate::out!(" -> after rescan {:.2} % ({} holes)", a.covered_pct, a.holes);
        }
        crate::outln!();
    }
    for d in &r.diagnostics {
        crate::outln!("note: {d}");
    }
    crate::outln!("report: {}", report_path.display());
    Ok(())
}

/// `depthmill scan --on-machine`: seed 003 on the simulated mill. The scanner is calibrated
/// against the machine's axes from the reference ball, then the part is shot at every A of the
/// options, each view tiled side by side, and every point placed by the chain.
fn run_on_machine(input: &Path, args: &ScanArgs, output: &Path) -> anyhow::Result<()> {
    use depthmill_geometry::PointCloud;
    use depthmill_geometry::formats::{PlyEncoding, write_ply};
    use depthmill_scanning::domain::chain::{
        AreaScannerSpec, ChainCalibration, ChainCalibrationOptions, ChainErrors, ChainScanOptions,
        MachineCell, MachineGeometry, calibrate_chain, place_on_rotor, scan_on_machine,
    };
    let opts: ChainScanOptions = match args.options.as_deref() {
        None => ChainScanOptions::default(),
        Some(path) => {
            let text =
                std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let de = &mut serde_json::Deserializer::from_str(&text);
            serde_path_to_error::deserialize(de)
                .map_err(|e| anyhow::anyhow!("{}: field {}: {}", path.display(), e.path(), e.inner()))?
        }
    };
    let (mesh, _) =
        read_mesh(input, &ReadLimits::default()).with_context(|| format!("{}", input.display()))?;
    let started = std::time::Instant::now();
    let cell =
        MachineCell::new(&MachineGeometry::default(), &ChainErrors::default(), AreaScannerSpec::default())
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    let drawing = ChainCalibration::nominal(cell.geometry());
    let cal = calibrate_chain(&cell, &drawing, &ChainCalibrationOptions::default())
        .map_err(|e| anyhow::anyhow!("calibrating the scanner against the machine: {e}"))?;
    if let Some(t) = cal.truth {
        crate::outln!(
            "scanner calibrated against the machine in {:.1} s of simulated scanning ({} shots of the reference ball): \
             chain placement error {:.4} mm before, {:.4} mm after",
            cal.scan_time_s,
            cal.shots,
            t.placement_error_before_mm,
            t.placement_error_mm
        );
    }
    let part = place_on_rotor(&mesh, 5.0);
    let (cloud, r) = scan_on_machine(&cell, &part, &cal.calibration, &opts)
        .map_err(|e| anyhow::anyhow!("{}: {e}", input.display()))?;
    let pc = PointCloud::from_points(cloud.points);
    let file = std::fs::File::create(output).with_context(|| format!("writing {}", output.display()))?;
    let comments =
        vec![format!("scanned on the mill; chain calibration reference {}", cal.calibration.reference)];
    write_ply(file, &pc, Some(cloud.shot.as_slice()), PlyEncoding::BinaryLittleEndian, &comments)
        .with_context(|| format!("writing {}", output.display()))?;
    let report_path = args.report.clone().unwrap_or_else(|| output.with_extension("scan.json"));
    let json = serde_json::json!({ "calibration": cal, "scan": r });
    std::fs::write(&report_path, serde_json::to_vec_pretty(&json)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    crate::outln!(
        "{}: {} points from {} shots at {} A positions; simulated scan time {:.1} s, wall {:.1} s",
        output.display(),
        r.points,
        r.shots,
        opts.a_angles_deg.len(),
        r.scan_time_s,
        started.elapsed().as_secs_f64()
    );
    crate::outln!(
        "merge error without markers (RMS after the best rigid fit to the part): {:.4} mm by the calibrated chain, \
         {:.4} mm by the drawing, {:.4} mm by the true chain (the scanner's noise alone)",
        r.registration.merge_rms_mm,
        r.registration_drawing.merge_rms_mm,
        r.registration_truth.merge_rms_mm
    );
    crate::outln!("report: {}", report_path.display());
    Ok(())
}
