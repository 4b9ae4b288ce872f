//! A whole scan on the cell: the rotary table driven over its protocol through
//! [`TableClient`] (a simulated controller on a socket, or a real one on a serial line behind the
//! same driver), the arm, latch and scanner simulated in [`ScanSession`].
//!
//! The table is indexed in real time (it is a device on a line: a 90° index at 45 °/s takes about
//! 2.3 s), the passes at each station are simulated as fast as the CPU allows, on blocking
//! threads so the async runtime stays responsive, while the table turns to the next station.

use std::sync::Arc;
use std::time::Duration;

use depthmill_geometry::Mesh;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio_util::sync::CancellationToken;

use crate::devices::table::TableClient;
use crate::domain::calibration::{
    Calibration, CalibrationError, CalibrationOptions, CalibrationReport, Cell,
};
use crate::domain::scan::{CellLayout, ScanError, ScanOptions, ScanOutput, ScanPlan, ScanSession};
use crate::domain::table::model::shortest_delta_deg;

/// Table speed for indexing, °/s (the controller's maximum).
pub const TABLE_SPEED_DEG_S: f64 = crate::domain::scan::plan::TABLE_INDEX_SPEED_DEG_S;
/// Table acceleration for indexing, °/s².
pub const TABLE_ACCEL_DEG_S2: f64 = crate::domain::scan::plan::TABLE_INDEX_ACCEL_DEG_S2;
/// Largest accepted difference between the settled encoder reading and the asked angle, degrees
/// (two encoder counts).
pub const TABLE_TOLERANCE_DEG: f64 = 0.0625;
/// Longest wait for the table to settle at a station.
pub const TABLE_TIMEOUT: Duration = Duration::from_secs(60);

/// Progress sink: fraction of the scan done (0..=1) and a message.
pub type Progress = Arc<dyn Fn(f64, String) + Send + Sync>;

fn internal(e: tokio::task::JoinError) -> ScanError {
    ScanError::Table(format!("a scan worker thread failed: {e}"))
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, ScanError> {
    tokio::task::spawn_blocking(f).await.map_err(internal)
}

/// Brings the table to `deg` and returns its settled encoder reading.
async fn index_table<S: AsyncRead + AsyncWrite + Unpin>(
    table: &mut TableClient<S>,
    deg: f64,
    cancel: &CancellationToken,
) -> Result<f64, ScanError> {
    let target = deg.rem_euclid(360.0);
    let terr = |e: crate::devices::table::TableError| ScanError::Table(e.to_string());
    table.move_to(target).await.map_err(terr)?;
    let measured = tokio::select! {
        r = table.wait_settled(TABLE_TOLERANCE_DEG, TABLE_TIMEOUT) => r.map_err(terr)?,
        () = cancel.cancelled() => return Err(ScanError::Cancelled),
    };
    let off = shortest_delta_deg(target, measured);
    if off.abs() > TABLE_TOLERANCE_DEG {
        return Err(ScanError::Table(format!(
            "asked for {target:.4}°, the encoder settled at {measured:.4}° ({off:+.4}°, tolerance {TABLE_TOLERANCE_DEG}°)"
        )));
    }
    Ok(measured)
}

/// Runs the stations of `plan`, indexing the table before each. A station's passes are
/// simulated (on a blocking thread, from the encoder reading the table settled at) while the
/// table already turns to the next station: the frames were latched at the settled angle, so
/// only their processing overlaps the turn, as on a real cell.
#[allow(clippy::too_many_arguments)]
async fn run_plan<S: AsyncRead + AsyncWrite + Unpin>(
    mut session: ScanSession,
    plan: &ScanPlan,
    rescan: bool,
    table: &mut TableClient<S>,
    progress: &Progress,
    span: (f64, f64),
    cancel: &CancellationToken,
) -> Result<ScanSession, ScanError> {
    let total = plan.passes().max(1);
    let mut done = 0usize;
    let n = plan.stations.len();
    let what = if rescan { "rescan station" } else { "station" };
    let turn = |k: usize, deg: f64, done: usize| {
        progress(
            span.0 + (span.1 - span.0) * done as f64 / total as f64,
            format!("{what} {}/{n}: turning the table to {deg:.1}°", k + 1),
        );
    };
    let mut measured = match plan.stations.first() {
        Some(first) => {
            turn(0, first.table_deg, 0);
            let waited = std::time::Instant::now();
            let m = index_table(table, first.table_deg, cancel).await?;
            session.add_table_wait(waited.elapsed().as_secs_f64());
            m
        }
        None => return Ok(session),
    };
    for (k, station) in plan.stations.iter().enumerate() {
        if cancel.is_cancelled() {
            return Err(ScanError::Cancelled);
        }
        let st = station.clone();
        let p = progress.clone();
        let c = cancel.clone();
        let base = done;
        let at = measured;
        let work = blocking(move || {
            let mut session = session;
            let r = session.run_station(
                &st,
                at,
                rescan,
                &mut |i, m| {
                    p(
                        span.0 + (span.1 - span.0) * (base + i) as f64 / total as f64,
                        format!("{what} {}/{n} at {at:.2}°: pass {i}/{m} done", k + 1),
                    )
                },
                &|| c.is_cancelled(),
            );
            (session, r)
        });
        done += station.passes.len();
        let next = plan.stations.get(k + 1).map(|s| s.table_deg);
        let ((s, r), next) = match next {
            Some(deg) => {
                turn(k + 1, deg, done);
                let indexing = async {
                    let waited = std::time::Instant::now();
                    let m = index_table(table, deg, cancel).await;
                    (m, waited.elapsed().as_secs_f64())
                };
                let (w, (m, secs)) = tokio::join!(work, indexing);
                (w?, Some((m, secs)))
            }
            None => (work.await?, None),
        };
        r?;
        session = s;
        if let Some((m, secs)) = next {
            measured = m?;
            session.add_table_wait(secs);
        }
    }
    Ok(session)
}

/// Runs the calibration routine on `cell` (its calibration in force places the scans) and fits
/// the new calibration; the table is indexed over its protocol as for a scan.
pub async fn run_calibration<S: AsyncRead + AsyncWrite + Unpin>(
    cell: Cell,
    layout: CellLayout,
    opts: CalibrationOptions,
    table: &mut TableClient<S>,
    progress: Progress,
    cancel: CancellationToken,
) -> Result<(Calibration, CalibrationReport), CalibrationError> {
    let scan_err = |e: ScanError| match e {
        ScanError::Cancelled => CalibrationError::Cancelled,
        ScanError::Table(m) => CalibrationError::Table(m),
        e => CalibrationError::Scan(e.to_string()),
    };
    progress(0.0, "planning the calibration scans".into());
    let terr = |e: crate::devices::table::TableError| CalibrationError::Table(e.to_string());
    // The views from where the table stands, in the given cyclic order.
    let mut opts = opts;
    let at = table.position_deg().await.map_err(terr)?;
    opts.table_angles_deg = crate::domain::scan::plan::visit_order(&opts.table_angles_deg, at);
    let (session, plan) =
        blocking(move || crate::domain::calibration::calibration_session(&cell, layout, &opts))
            .await
            .map_err(scan_err)??;
    table.set_speed(TABLE_SPEED_DEG_S).await.map_err(terr)?;
    table.set_accel(TABLE_ACCEL_DEG_S2).await.map_err(terr)?;
    let session =
        run_plan(session, &plan, false, table, &progress, (0.0, 0.9), &cancel).await.map_err(scan_err)?;
    progress(0.9, "fitting the table and the scanner mount".into());
    let (cal, report) = blocking(move || session.finish_calibration()).await.map_err(scan_err)??;
    progress(
        1.0,
        format!(
            "calibrated: merge error {:.4} mm",
            report.registration_after.map_or(0.0, |r| r.merge_rms_mm)
        ),
    );
    Ok((cal, report))
}

/// A scan session on `cell` and its plan, made on a blocking thread.
async fn planned(
    mesh: Arc<Mesh>,
    opts: ScanOptions,
    layout: CellLayout,
    cell: Cell,
) -> Result<(ScanSession, ScanPlan), ScanError> {
    blocking(move || {
        let mut s = ScanSession::with_cell(&mesh, opts, layout, cell)?;
        let plan = s.plan()?;
        Ok::<_, ScanError>((s, plan))
    })
    .await?
}

/// A calibration made for a scan: the cell calibrated at the scan's own stations (the table
/// turning once for both) or, when that cannot be done, by the routine before it.
#[derive(Debug, Clone)]
pub struct MadeCalibration {
    pub calibration: Calibration,
    pub report: CalibrationReport,
    /// Why it was not made at the scan's stations (then the routine ran before the scan).
    pub why_not: Option<String>,
}

impl MadeCalibration {
    /// Made at the scan's own stations.
    pub fn during_scan(&self) -> bool {
        self.why_not.is_none()
    }
}

/// Scans `mesh` with `opts` on `cell` (the physics on its truth, the points placed with its
/// calibration): plan, stations, and the adaptive rescan when asked. With `calibrate`, the cell
/// is calibrated for this scan first ([`MadeCalibration`]): at the scan's stations when the part
/// leaves the reference sphere's nest free and the stations suit the routine, else by the routine
/// before the scan; the points are placed with the new calibration either way.
#[allow(clippy::too_many_arguments)]
pub async fn run_scan<S: AsyncRead + AsyncWrite + Unpin>(
    mesh: Mesh,
    opts: ScanOptions,
    layout: CellLayout,
    cell: Cell,
    calibrate: Option<CalibrationOptions>,
    table: &mut TableClient<S>,
    progress: Progress,
    cancel: CancellationToken,
) -> Result<(ScanOutput, Option<MadeCalibration>), ScanError> {
    progress(0.0, format!("planning over a {}-triangle mesh", mesh.triangles.len()));
    let terr = |e: crate::devices::table::TableError| ScanError::Table(e.to_string());
    // The automatic stations from where the table stands (after a calibration or another job),
    // in the given cyclic order; explicit passes keep theirs.
    let mut opts = opts;
    if opts.passes.is_none() {
        let at = table.position_deg().await.map_err(terr)?;
        opts.table_angles_deg = crate::domain::scan::plan::visit_order(&opts.table_angles_deg, at);
    }
    let mesh = Arc::new(mesh);
    let in_scan = match calibrate.clone() {
        None => None,
        Some(cal) => {
            let (m, o, c) = (mesh.clone(), opts.clone(), cell.clone());
            Some(
                blocking(move || {
                    let mut s = ScanSession::with_cell_calibrating(&m, o, layout, c, cal)?;
                    let plan = s.plan()?;
                    Ok::<_, ScanError>((s, plan))
                })
                .await?,
            )
        }
    };
    let mut made = None;
    let mut progress = progress;
    let (session, plan) = match in_scan {
        Some(Ok(found)) => found,
        Some(Err(ScanError::NotInScan(why))) => {
            // The routine first, then the scan placed with what it found.
            tracing::info!(reason = %why, "calibrating the cell before the scan");
            let cal_opts = calibrate.clone().unwrap_or_default();
            let sub: Progress = {
                let p = progress.clone();
                Arc::new(move |f, m| p(0.3 * f, format!("calibrating the cell: {m}")))
            };
            let (c, report) = run_calibration(cell.clone(), layout, cal_opts, table, sub, cancel.clone())
                .await
                .map_err(|e| match e {
                    CalibrationError::Cancelled => ScanError::Cancelled,
                    CalibrationError::Table(m) => ScanError::Table(m),
                    e => ScanError::Calibration(e.to_string()),
                })?;
            let cell = Cell { calibration: Some(c), ..cell };
            made = Some(MadeCalibration { calibration: c, report, why_not: Some(why) });
            // The scan's own progress goes on from where the routine's ended.
            let p = progress.clone();
            progress = Arc::new(move |f, m| p(0.3 + 0.7 * f, m));
            if opts.passes.is_none() {
                let at = table.position_deg().await.map_err(terr)?;
                opts.table_angles_deg = crate::domain::scan::plan::visit_order(&opts.table_angles_deg, at);
            }
            planned(mesh.clone(), opts, layout, cell).await?
        }
        Some(Err(e)) => return Err(e),
        None => planned(mesh.clone(), opts, layout, cell).await?,
    };
    tracing::info!(
        stations = plan.stations.len(),
        passes = plan.passes(),
        length_mm = plan.length_mm(),
        "scan planned"
    );
    table.set_speed(TABLE_SPEED_DEG_S).await.map_err(terr)?;
    table.set_accel(TABLE_ACCEL_DEG_S2).await.map_err(terr)?;
    let adaptive = session.options().adaptive_rescan;
    let first_span = if adaptive { (0.0, 0.75) } else { (0.0, 1.0) };
    // The table stays at the last station: the rescan's views are chosen from there (its own
    // angle costs no turn).
    let table_at = plan.stations.last().map_or(0.0, |s| s.table_deg);
    let mut session = run_plan(session, &plan, false, table, &progress, first_span, &cancel).await?;
    if session.calibrating_in_scan() {
        progress(first_span.1 * 0.97, "fitting the table and the scanner mount to the sphere's scans".into());
        let (s, fitted) = blocking(move || {
            let mut session = session;
            let r = session.calibrate_in_scan();
            (session, r)
        })
        .await?;
        session = s;
        let (c, report) = fitted?;
        made = Some(MadeCalibration { calibration: c, report, why_not: None });
    }
    if adaptive {
        progress(0.75, "coverage map of the first scan".into());
        let (s, found) = blocking(move || {
            let mut session = session;
            let r = session.holes().map(|(before, targets)| {
                let plan = session.rescan_plan(&targets, table_at);
                (before, targets, plan)
            });
            (session, r)
        })
        .await?;
        let (before, targets, rescan) = found?;
        session = s;
        tracing::info!(
            covered_pct = before.covered_pct,
            holes = before.holes,
            targets = targets.len(),
            passes = rescan.passes(),
            "adaptive rescan"
        );
        if rescan.passes() == 0 {
            session.note(format!(
                "adaptive rescan: {} holes found, none worth a pass or reachable",
                before.holes
            ));
            session.record_rescan(before, None, targets);
        } else {
            session = run_plan(session, &rescan, true, table, &progress, (0.78, 0.98), &cancel).await?;
            let (s, after) = blocking(move || {
                let r = session.holes().map(|(a, _)| a);
                (session, r)
            })
            .await?;
            session = s;
            session.record_rescan(before, Some(after?), targets);
        }
    }
    let out = session.finish();
    progress(1.0, format!("{} points from {} frames", out.report.points, out.report.frames));
    Ok((out, made))
}
