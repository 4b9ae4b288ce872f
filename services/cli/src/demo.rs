//! `depthmill demo`: the whole product on the sample part, in one command.
//!
//! Starts the embedded stack, writes the generated sample part (`part.stl`), submits a
//! scan-to-part job over REST (dynamic scan with an adaptive rescan, clean-up, depth and roughing
//! maps, roughing and finishing G-code, execution on the simulated EMCO under the adaptive loop,
//! report), follows it stage by stage, then writes every artifact, `job.json`, the HTML report and
//! its pictures into the output folder and prints where everything is and how long each stage
//! took.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use futures::StreamExt as _;
use serde_json::{Value, json};

/// Options of `depthmill demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Output folder (artifacts, job.json, report.html, report/).
    #[arg(short, long, default_value = "depthmill-demo")]
    pub output: PathBuf,
    /// Where the stack keeps its database and artifacts (default: OUTPUT/data).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Replace the job's sections with those of this JSON file (a job request without `input`).
    #[arg(long)]
    pub options: Option<PathBuf>,
    /// Make this part (STL, or PLY with faces) instead of the sample relief. The job is the
    /// demo's with the stock sized from the part (unless --options gives one).
    #[arg(long)]
    pub part: Option<PathBuf>,
    /// Length unit of --part: auto (default), mm, m or in.
    #[arg(long, requires = "part")]
    pub units: Option<String>,
}

/// The demo job, minus its input.
pub fn demo_job() -> Value {
    json!({
        "name": "demo: sample relief",
        "scan": {"mode": "dynamic", "table_angles_deg": [0, 90, 180, 270], "standoff_mm": 150,
                 "line_rate_hz": 150, "line_spacing_mm": 0.25, "adaptive_rescan": true},
        "reconstruct": {"pixel_mm": 0.25, "faces": [{"view": "+Z"}],
                        "fill": {"method": "idw", "max_hole_mm": 2.0}},
        "plan": {"stock": {"z_mm": 13, "material": "aluminium"},
                 "roughing": {"tool": "flat-6", "step_down_mm": 2.5, "stock_to_leave_mm": 0.3},
                 "finishing": {"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.5,
                               "tolerance_mm": 0.01, "arcs": true},
                 "dialect": "linuxcnc"},
        "execute": {"machine": "emco-f1", "adaptive": "aco"}
    })
}

fn http() -> anyhow::Result<reqwest::Client> {
    depthmill_common::tls::http_client()
        .timeout(Duration::from_secs(600))
        .build()
        .context("building the HTTP client")
}

async fn json_of(resp: reqwest::Response, what: &str) -> anyhow::Result<Value> {
    let status = resp.status();
    let body = resp.text().await.with_context(|| format!("{what}: reading the reply"))?;
    if !status.is_success() {
        bail!("{what} failed: {status} {body}");
    }
    serde_json::from_str(&body).with_context(|| format!("{what}: the reply is not JSON"))
}

pub async fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let out = &args.output;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let data_dir = args.data_dir.clone().unwrap_or_else(|| out.join("data"));

    // The part.
    let part = match &args.part {
        Some(path) => {
            let (_, media_type) =
                crate::client::classify(path).filter(|(kind, _)| *kind == "mesh").with_context(|| {
                    format!("{}: --part takes a mesh (.stl, .obj, .off, or .ply with faces; each may be gzip-compressed, .stl.gz)", path.display())
                })?;
            let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            let (geometry, stats) = depthmill_geometry::formats::read_any_from(
                std::io::Cursor::new(&bytes),
                &path.display().to_string(),
                Some(bytes.len() as u64),
                &depthmill_geometry::formats::ReadLimits::default(),
            )?;
            let extent = match &geometry {
                depthmill_geometry::formats::Geometry::Mesh(m) => m.bounds().map(|b| b.extent()),
                depthmill_geometry::formats::Geometry::Cloud(_) => None,
            }
            .with_context(|| format!("{}: holds no triangles", path.display()))?;
            crate::outln!(
                "part: {} ({} triangles, {:.3} x {:.3} x {:.3} in its units)",
                path.display(),
                stats.triangles,
                extent.x,
                extent.y,
                extent.z
            );
            Part { bytes, media_type, name: path.file_stem().map(|s| s.to_string_lossy().into_owned()) }
        }
        None => {
            let mesh = depthmill_geometry::sample::sample_relief(0.25);
            let mut stl = Vec::new();
            depthmill_geometry::formats::write_stl(&mut stl, &mesh, depthmill_geometry::sample::STL_HEADER)?;
            let part_path = out.join("part.stl");
            std::fs::write(&part_path, &stl).with_context(|| format!("writing {}", part_path.display()))?;
            crate::outln!(
                "part: {} ({} triangles, 80 x 60 mm relief)",
                part_path.display(),
                mesh.triangles.len()
            );
            Part { bytes: stl, media_type: "model/stl", name: None }
        }
    };

    // The stack.
    let stack =
        crate::embedded::start(data_dir.clone(), None, "127.0.0.1:0".parse()?, "127.0.0.1:0".parse()?, None)
            .await?;
    let base = format!("http://{}", stack.rest_addr);
    crate::outln!("stack: REST on {base}, data in {}", data_dir.display());
    let result = drive(&base, part, args, out).await;
    stack.stop().await.context("stopping the stack")?;
    let summary = result?;
    crate::outln!("{summary}");
    crate::outln!("demo wall time {:.1} s (target: under 20 s in release)", started.elapsed().as_secs_f64());
    Ok(())
}

/// Wall time the scan spent waiting for the table, from the fetched scan report.
fn scan_table_wait(out: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(out.join("artifacts").join("scan_report.json")).ok()?;
    serde_json::from_str::<Value>(&text).ok()?["table_wait_s"].as_f64()
}

/// The part the demo makes: its file's bytes and media type, and its name when not the sample.
struct Part {
    bytes: Vec<u8>,
    media_type: &'static str,
    name: Option<String>,
}

/// The demo job for a part of the user's: the sample's sections with the faces chosen from the
/// part's shape (`reconstruct.face_choice`), the stock sized from the part (its top at the part's
/// highest point, the CAM's default) instead of the sample's 13 mm, and the tools left to the CAM (the same defaults, replaced by longer-reaching ones of the
/// library when they cannot reach the part; the plan report says why).
pub fn part_job(name: &str) -> Value {
    let mut job = demo_job();
    job["name"] = json!(format!("demo: {name}"));
    // The faces come from the part's shape: the fewest A-axis turns that reach its surface.
    if let Some(rec) = job["reconstruct"].as_object_mut() {
        rec.remove("faces");
        rec.insert("face_choice".into(), json!({}));
    }
    if let Some(stock) = job["plan"]["stock"].as_object_mut() {
        stock.remove("z_mm");
    }
    for op in ["roughing", "finishing"] {
        if let Some(o) = job["plan"][op].as_object_mut() {
            o.remove("tool");
        }
    }
    job
}

/// Uploads, submits, follows and collects; returns the closing summary.
async fn drive(base: &str, part: Part, args: &DemoArgs, out: &Path) -> anyhow::Result<String> {
    let client = http()?;
    let up = client
        .post(format!("{base}/v1/artifacts"))
        .header("content-type", part.media_type)
        .body(part.bytes)
        .send()
        .await
        .context("uploading the part")?;
    let up = json_of(up, "upload").await?;
    let sha = up["sha256"].as_str().context("upload reply without sha256")?.to_string();
    let mut job = match &args.options {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            serde_json::from_str::<Value>(&text).with_context(|| format!("{}: not JSON", p.display()))?
        }
        None => match &part.name {
            Some(name) => part_job(name),
            None => demo_job(),
        },
    };
    job["input"] = json!({"kind": "mesh", "artifact": sha});
    if let Some(u) = &args.units {
        job["input"]["units"] = json!(u);
    }
    std::fs::write(out.join("job-request.json"), serde_json::to_vec_pretty(&job)?)?;
    let created =
        json_of(client.post(format!("{base}/v1/jobs")).json(&job).send().await?, "submitting the job")
            .await?;
    let id = created["id"].as_str().context("job reply without id")?.to_string();
    crate::outln!("job {id} submitted");

    // Follow it: one line per stage as it ends, progress in between.
    let mut printed: Vec<String> = Vec::new();
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("  [{elapsed_precise}] {bar:30} {percent:>3}% {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let done = loop {
        let j = json_of(client.get(format!("{base}/v1/jobs/{id}")).send().await?, "reading the job").await?;
        if let Some(t) = j["stage_timings_s"].as_object() {
            for (stage, secs) in t {
                if !printed.contains(stage) {
                    printed.push(stage.clone());
                    bar.println(format!("  {stage:<12} done in {:>6.2} s", secs.as_f64().unwrap_or(0.0)));
                }
            }
        }
        bar.set_position((j["progress"].as_f64().unwrap_or(0.0) * 1000.0) as u64);
        bar.set_message(format!(
            "{} {}",
            j["status"].as_str().unwrap_or("?"),
            j["stage"].as_str().unwrap_or("?")
        ));
        match j["status"].as_str() {
            Some("succeeded" | "failed" | "cancelled") => break j,
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    };
    bar.finish_and_clear();
    std::fs::write(out.join("job.json"), serde_json::to_vec_pretty(&done)?)?;
    if done["status"] != "succeeded" {
        bail!(
            "job {id} {}: {} ({})",
            done["status"].as_str().unwrap_or("?"),
            done["error"]["message"].as_str().unwrap_or("no message"),
            done["error"]["stage"].as_str().unwrap_or("?")
        );
    }

    // Every artifact into OUT/artifacts, the report and its pictures into OUT.
    let art_dir = out.join("artifacts");
    std::fs::create_dir_all(&art_dir)?;
    let mut bytes_of = std::collections::BTreeMap::new();
    let mut listing = Vec::new();
    // Downloaded four at a time, each written as it arrives; listed in the job's order.
    let wanted: Vec<(String, String, String)> = done["artifacts"]
        .as_object()
        .map(|arts| {
            arts.iter()
                .map(|(name, a)| {
                    let sha = a["sha256"].as_str().unwrap_or_default().to_string();
                    let media = a["media_type"].as_str().unwrap_or("").to_string();
                    (name.clone(), sha, media)
                })
                .collect()
        })
        .unwrap_or_default();
    let fetched: Vec<anyhow::Result<(String, PathBuf, Vec<u8>)>> =
        futures::stream::iter(wanted.into_iter().map(|(name, sha, media)| {
            let (client, art_dir) = (&client, &art_dir);
            async move {
                let resp = client.get(format!("{base}/v1/artifacts/{sha}")).send().await?;
                if !resp.status().is_success() {
                    bail!("downloading {name}: {}", resp.status());
                }
                let bytes = resp.bytes().await?.to_vec();
                let path = art_dir.join(crate::client::artifact_file_name(&name, &media));
                tokio::fs::write(&path, &bytes)
                    .await
                    .with_context(|| format!("writing {}", path.display()))?;
                Ok((name, path, bytes))
            }
        }))
        .buffered(4)
        .collect()
        .await;
    for f in fetched {
        let (name, path, bytes) = f?;
        listing.push(format!("  {name:<18} {}", path.display()));
        if name != "report" && name != "report_json" {
            bytes_of.insert(name, bytes);
        }
    }
    let report = tokio::task::spawn_blocking(move || {
        depthmill_report::render(&depthmill_report::ReportInput {
            job: &done,
            artifacts: &bytes_of,
            digests: &depthmill_report::digest::Digests::NONE,
        })
        .map(|r| (r, done))
    })
    .await??;
    let (report, done) = report;
    let report_path = out.join("report.html");
    std::fs::write(&report_path, report.html.as_bytes())?;
    let pics = out.join("report");
    std::fs::create_dir_all(&pics)?;
    for (name, bytes) in &report.files {
        std::fs::write(pics.join(name), bytes)?;
    }

    let m = &done["metrics"];
    let f = |k: &str| m[k].as_f64().map_or("-".to_string(), |v| format!("{v:.3}"));
    let mut s = String::new();
    s.push_str(&format!("job {id} succeeded\n"));
    s.push_str("stage timings (s):");
    let mut total = 0.0;
    for stage in ["scan", "reconstruct", "plan", "execute", "report"] {
        if let Some(v) = done["stage_timings_s"][stage].as_f64() {
            total += v;
            s.push_str(&format!(" {stage} {v:.2},"));
        }
    }
    s.push_str(&format!(" total {total:.2}\n"));
    if let Some(wait) = scan_table_wait(out) {
        s.push_str(&format!(
            "  (of the scan, {wait:.1} s is the rotary table turning between stations in real time)\n"
        ));
    }
    s.push_str(&format!(
        "scan: {} points, coverage {} %, registration RMS {} mm, merge RMS {} mm (cell calibration version {})\n",
        m["scan_points"].as_f64().map_or("-".to_string(), |v| format!("{v:.0}")),
        f("scan_coverage_pct"),
        f("scan_registration_rms_mm"),
        f("scan_registration_merge_rms_mm"),
        m["scan_calibration_version"].as_f64().map_or("-".to_string(), |v| format!("{v:.0}"))
    ));
    s.push_str(&format!(
        "part: depth-map coverage {} %, max gouge {} mm, max leftover {} mm, RMS deviation {} mm\n",
        f("coverage_pct"),
        f("max_gouge_mm"),
        f("max_leftover_mm"),
        f("rms_deviation_mm")
    ));
    if m["part_off_walls_mean_mm"].is_f64() {
        let g = |k: &str| m[k].as_f64().map_or("-".to_string(), |v| format!("{v:+.4}"));
        s.push_str(&format!(
            "against the original part off the walls: mean {} mm, RMS {} mm, max gouge {} mm; against the part opened by the finest tool where it reaches: mean {} mm, RMS {} mm, max gouge {} mm{}\n",
            g("part_off_walls_mean_mm"),
            g("part_off_walls_rms_mm"),
            g("part_off_walls_max_gouge_mm"),
            g("part_opened_mean_mm"),
            g("part_opened_rms_mm"),
            g("part_opened_max_gouge_mm"),
            match (m["part_opened_max_gouge_x_mm"].as_f64(), m["part_opened_max_gouge_y_mm"].as_f64()) {
                (Some(x), Some(y)) => format!(" at ({x:.2}, {y:.2}) mm"),
                _ => String::new(),
            },
        ));
        if m["part_opened_measured_mean_mm"].is_f64() {
            s.push_str(&format!(
                "  of which where the scan measured: mean {} mm, RMS {} mm, max gouge {} mm\n",
                g("part_opened_measured_mean_mm"),
                g("part_opened_measured_rms_mm"),
                g("part_opened_measured_max_gouge_mm"),
            ));
        }
    }
    s.push_str(&format!(
        "cycle time: {} s with the adaptive loop, {} s without\n",
        f("cycle_time_s"),
        f("cycle_time_no_adaptive_s")
    ));
    s.push_str("artifacts:\n");
    s.push_str(&listing.join("\n"));
    s.push_str(&format!(
        "\nreport: {} (pictures in {}; served at {base}/v1/jobs/{id}/report while the stack runs)",
        report_path.display(),
        pics.display()
    ));
    Ok(s)
}
