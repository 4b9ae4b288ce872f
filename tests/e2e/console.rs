//! The operator console in a real browser (Debian's `chromium` driven by `chromedriver` over
//! WebDriver, through fantoccini): a part file is dropped on the submit page, the form generated
//! from `/openapi.json` is filled and sent, the job is watched to the end, its 3-D view and
//! telemetry open; a bad file shows the server's error; a server that requires tokens gets one
//! through the page's prompt. No console errors on any page.
//!
//! `DEPTHMILL_CONSOLE_SHOTS=DIR` keeps the screenshots (the README's pictures come from here).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use depthmill_orchestrator::auth::{AuthConfig, AuthMode};
use depthmill_tests::{StackOptions, TestStack};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};

const JOB_WAIT: Duration = Duration::from_secs(120);

fn on_path(names: &[&str]) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).flat_map(|d| names.iter().map(move |n| d.join(n))).find(|p| p.is_file())
}

/// chromedriver and the browser, or `None` (the test is skipped) unless
/// `DEPTHMILL_REQUIRE_CHROMIUM=1` makes their absence a failure.
fn browser_or_skip() -> Option<(PathBuf, PathBuf)> {
    let found = on_path(&["chromedriver"]).zip(on_path(&["chromium", "chromium-browser", "google-chrome"]));
    if found.is_none() {
        assert!(
            std::env::var("DEPTHMILL_REQUIRE_CHROMIUM").as_deref() != Ok("1"),
            "DEPTHMILL_REQUIRE_CHROMIUM=1 but chromedriver or chromium is not on PATH (Debian: chromium chromium-driver)"
        );
        eprintln!("skipped: no chromedriver/chromium on PATH");
    }
    found
}

/// A chromedriver on a free loopback port, killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn start_driver(chromedriver: &Path) -> anyhow::Result<Driver> {
    let port = crate::children::free_addr()?.port();
    let child = Command::new(chromedriver)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()?;
    let driver = Driver { child, url: format!("http://127.0.0.1:{port}") };
    let http = reqwest::Client::new();
    for _ in 0..100 {
        if http.get(format!("{}/status", driver.url)).send().await.is_ok_and(|r| r.status().is_success()) {
            return Ok(driver);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!("chromedriver did not start on port {port}")
}

async fn browser(driver: &Driver, chromium: &Path, width: u32, height: u32) -> anyhow::Result<Client> {
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({"binary": chromium, "args": ["--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
            format!("--window-size={width},{height}")]}),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    Ok(ClientBuilder::new(connector).capabilities(caps).connect(&driver.url).await?)
}

/// Polls `script` (a function body returning a value) until it returns something truthy.
async fn until(c: &Client, what: &str, timeout: Duration, script: &str) -> anyhow::Result<Value> {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let v = c.execute(script, vec![]).await?;
        let truthy = match &v {
            Value::Null | Value::Bool(false) => false,
            Value::String(s) => !s.is_empty(),
            _ => true,
        };
        if truthy {
            return Ok(v);
        }
        if tokio::time::Instant::now() > deadline {
            let text = c.execute("return document.body.innerText", vec![]).await.unwrap_or_default();
            anyhow::bail!(
                "timed out waiting for {what}; the page says:\n{}",
                text.as_str().unwrap_or_default()
            );
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

async fn console_errors(c: &Client) -> anyhow::Result<Vec<String>> {
    let v = c.execute("return window.__consoleErrors || ['no error hook']", vec![]).await?;
    Ok(serde_json::from_value(v)?)
}

/// Saves a screenshot when `DEPTHMILL_CONSOLE_SHOTS` names a folder.
fn keep(name: &str, png: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = std::env::var_os("DEPTHMILL_CONSOLE_SHOTS") {
        std::fs::create_dir_all(&dir)?;
        std::fs::write(Path::new(&dir).join(name), png)?;
    }
    Ok(())
}

/// Distinct colours and the share of pixels unlike the viewer's background (#1b2128).
fn picture_stats(png_bytes: &[u8]) -> anyhow::Result<(usize, f64)> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(png_bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info()?;
    let mut buf = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader.next_frame(&mut buf)?;
    let channels = info.color_type.samples();
    let mut colours = std::collections::HashSet::new();
    let mut drawn = 0usize;
    let px = &buf[..info.buffer_size()];
    for p in px.chunks(channels) {
        let rgb = [p[0], p[1], p[2]];
        colours.insert(rgb);
        let d = (i32::from(rgb[0]) - 0x1b).abs()
            + (i32::from(rgb[1]) - 0x21).abs()
            + (i32::from(rgb[2]) - 0x28).abs();
        if d > 30 {
            drawn += 1;
        }
    }
    Ok((colours.len(), drawn as f64 / (px.len() / channels).max(1) as f64))
}

#[tokio::test]
async fn the_console_submits_watches_and_shows_a_job() -> anyhow::Result<()> {
    let Some((chromedriver, chromium)) = browser_or_skip() else { return Ok(()) };
    let stack = TestStack::start().await?;
    let driver = start_driver(&chromedriver).await?;
    let c = browser(&driver, &chromium, 1280, 800).await?;
    let dir = tempfile::tempdir()?;
    let part = dir.path().join("dome.stl");
    std::fs::write(&part, crate::scan::dome_stl())?;

    // Submit: the file, then the sections of the form the API description generates.
    c.goto(&stack.url("/#/submit")).await?;
    c.wait().for_element(Locator::Css("#drop-zone")).await?;
    c.find(Locator::Css("#file-input")).await?.send_keys(&part.to_string_lossy()).await?;
    c.wait().at_most(Duration::from_secs(20)).for_element(Locator::Css("#job-form")).await?;
    let status = c.find(Locator::Css("#file-status")).await?.text().await?;
    assert!(status.contains("uploaded") && status.contains("scan stage"), "{status}");
    keep("console-submit.png", &c.screenshot().await?)?;
    // Every input has a label.
    let unlabelled = c
        .execute(
            "return [...document.querySelectorAll('#job-form input, #job-form select, #job-form textarea')]
               .filter(e => !document.querySelector(`label[for=\"${e.id}\"]`)).map(e => e.id)",
            vec![],
        )
        .await?;
    assert_eq!(unlabelled, json!([]), "inputs without a label");
    // A quick job: coarse scan lines and maps, large tools.
    for section in ["scan", "reconstruct", "plan"] {
        c.find(Locator::Css(&format!("details[data-section=\"{section}\"] > summary")))
            .await?
            .click()
            .await?;
    }
    for (field, value) in [
        ("scan.table_angles_deg", "[90]"),
        ("scan.line_spacing_mm", "1.0"),
        ("reconstruct.pixel_mm", "0.5"),
        ("plan.stock.z_mm", "8"),
        ("plan.roughing.tool", "flat-6"),
        ("plan.roughing.step_down_mm", "3"),
        ("plan.finishing.tool", "ball-6"),
        ("plan.finishing.step_over_mm", "2"),
    ] {
        let input =
            c.find(Locator::Css(&format!("[data-field=\"{field}\"]:is(input, textarea, select)"))).await?;
        input.send_keys(value).await?;
    }
    c.find(Locator::Css("#submit-job")).await?.click().await?;

    // The job page, live until the end.
    let id = until(
        &c,
        "the job page",
        Duration::from_secs(20),
        "return location.hash.match(/^#\\/jobs\\/(.+)/)?.[1]",
    )
    .await?;
    let id = id.as_str().unwrap_or_default().to_string();
    let status = until(
        &c,
        "the job to end",
        JOB_WAIT,
        "const b = document.querySelector('#main .card .badge'); return b && !['queued','running'].includes(b.textContent) && b.textContent",
    )
    .await?;
    let job: Value = stack.http.get(stack.url(&format!("/v1/jobs/{id}"))).send().await?.json().await?;
    assert_eq!(status, "succeeded", "{job}");
    assert_eq!(job["spec"]["plan"]["finishing"]["tool"], "ball-6", "the form's values were sent: {job}");
    assert_eq!(job["spec"]["scan"]["table_angles_deg"], json!([90.0]), "{job}");
    // Attempts and artifacts listed.
    let attempts = c.find_all(Locator::Css("#attempts tbody tr")).await?;
    assert!(attempts.len() >= 5, "{} attempt rows", attempts.len());
    // What the stages said: the scan at least says which rays gave no point.
    let diagnostics = c.find(Locator::Css("#diagnostics")).await?.text().await?;
    assert!(diagnostics.contains("dropped_rays"), "{diagnostics}");
    assert_eq!(
        c.find_all(Locator::Css("#diagnostics tbody tr")).await?.len(),
        job["diagnostics"].as_array().map_or(0, Vec::len),
        "{job}"
    );
    let artifacts = c.find(Locator::Css("#artifacts")).await?.text().await?;
    for name in ["point_cloud", "depth_map", "gcode", "telemetry", "report"] {
        assert!(artifacts.contains(name), "{name} not listed: {artifacts}");
    }

    // The 3-D view: cloud, depth map and toolpaths drawn.
    c.find(Locator::Css("#tab-view")).await?.click().await?;
    let notes = until(&c, "the 3-D view", Duration::from_secs(30),
        "const v = document.querySelector('#viewer'); const s = document.querySelector('#viewer-status'); return v && v.dataset.frames && s && s.textContent").await?;
    let notes = notes.as_str().unwrap_or_default().to_string();
    assert!(notes.contains("points") && notes.contains("passes"), "{notes}");
    let layers = c.find(Locator::Css("#viewer")).await?.attr("data-layers").await?.unwrap_or_default();
    assert_eq!(layers, "cloud map paths machined", "layers offered");
    let viewer = c.find(Locator::Css("#viewer")).await?;
    let shot = viewer.screenshot().await?;
    let (colours, drawn) = picture_stats(&shot)?;
    assert!(
        colours > 200 && drawn > 0.05,
        "the view is drawn: {colours} colours, {:.1} % drawn",
        drawn * 100.0
    );
    // Pan with the arrow keys: the picture changes.
    let canvas = c.find(Locator::Css("#viewer canvas")).await?;
    canvas.click().await?;
    canvas.send_keys("\u{E012}\u{E012}\u{E012}").await?; // arrow left: pan
    let turned = viewer.screenshot().await?;
    assert_ne!(shot, turned, "the keys move the view");
    keep("console-job.png", &c.screenshot().await?)?;

    // Telemetry over time, with the adaptive loop's active limits.
    c.find(Locator::Css("#tab-telemetry")).await?.click().await?;
    until(
        &c,
        "the telemetry charts",
        Duration::from_secs(20),
        "return document.querySelectorAll('#telemetry .uplot').length >= 3",
    )
    .await?;
    let limits = c.find(Locator::Css("#active-limits")).await?.text().await?;
    assert!(!limits.is_empty());
    keep("console-telemetry.png", &c.screenshot().await?)?;

    // The list shows it; the compare page puts it beside itself.
    c.goto(&stack.url("/#/jobs")).await?;
    until(
        &c,
        "the job list",
        Duration::from_secs(10),
        &format!("return document.querySelector('tr[data-id=\"{id}\"]')"),
    )
    .await?;
    keep("console-jobs.png", &c.screenshot().await?)?;
    c.goto(&stack.url(&format!("/#/compare?a={id}&b={id}"))).await?;
    let table = until(
        &c,
        "the comparison",
        Duration::from_secs(10),
        "return document.querySelector('#compare-table')?.innerText",
    )
    .await?;
    assert!(table.as_str().unwrap_or_default().contains("Cycle time"), "{table}");

    assert_eq!(console_errors(&c).await?, Vec::<String>::new(), "errors in the page");
    c.close().await?;
    drop(driver);
    stack.shutdown().await
}

#[tokio::test]
async fn the_console_shows_the_server_s_error_for_a_bad_file_and_asks_for_a_token() -> anyhow::Result<()> {
    let Some((chromedriver, chromium)) = browser_or_skip() else { return Ok(()) };
    let stack = TestStack::start_with(StackOptions {
        auth: AuthConfig { mode: AuthMode::Tokens, cache_s: 0.0 },
        ..Default::default()
    })
    .await?;
    let token = stack.issue_token("console test", "submit").await?.token;
    let driver = start_driver(&chromedriver).await?;
    // A tablet's width.
    let c = browser(&driver, &chromium, 820, 1180).await?;
    let dir = tempfile::tempdir()?;

    // The page asks for a token, once, and keeps it for the session.
    c.goto(&stack.url("/#/jobs")).await?;
    until(
        &c,
        "the token prompt",
        Duration::from_secs(10),
        "return document.querySelector('#token-dialog').open",
    )
    .await?;
    c.find(Locator::Css("#token-input")).await?.send_keys(&token).await?;
    c.find(Locator::Css("#token-form button[type=submit]")).await?.click().await?;
    until(&c, "the job list", Duration::from_secs(10), "return document.querySelector('#jobs-table')")
        .await?;
    let kept = c.execute("return sessionStorage.getItem('depthmill.token')", vec![]).await?;
    assert_eq!(kept, json!(token), "kept for the session");
    let local = c.execute("return localStorage.length", vec![]).await?;
    assert_eq!(local, json!(0), "nothing kept beyond the session");

    // A file of an unknown type: said at once, nothing uploaded.
    c.goto(&stack.url("/#/submit")).await?;
    let odd = dir.path().join("part.step");
    std::fs::write(&odd, "ISO-10303-21;\nHEADER;\nENDSEC;\n")?;
    c.wait().for_element(Locator::Css("#file-input")).await?.send_keys(&odd.to_string_lossy()).await?;
    let said = until(
        &c,
        "the type error",
        Duration::from_secs(10),
        "return document.querySelector('#file-status.error')?.textContent",
    )
    .await?;
    assert!(said.as_str().unwrap_or_default().contains("part.step"), "{said}");

    // A gzip-compressed PLY with faces: a mesh, told from the decompressed header, uploaded as it is.
    let ply_gz = dir.path().join("tri.ply.gz");
    let mut gz =
        flate2::write::GzEncoder::new(std::fs::File::create(&ply_gz)?, flate2::Compression::default());
    std::io::Write::write_all(
        &mut gz,
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 2\n3 0 1 2\n",
    )?;
    gz.finish()?;
    c.find(Locator::Css("#file-input")).await?.send_keys(&ply_gz.to_string_lossy()).await?;
    let said = until(
        &c,
        "the gzip upload",
        Duration::from_secs(20),
        "const s = document.querySelector('#file-status')?.textContent || ''; return s.includes('uploaded') ? s : null",
    )
    .await?;
    let said = said.as_str().unwrap_or_default();
    assert!(said.contains("tri.ply.gz") && said.contains("a mesh starts at the scan stage"), "{said}");
    c.refresh().await?;
    c.wait().for_element(Locator::Css("#file-input")).await?;

    // A mesh whose every triangle is degenerate: uploaded, then refused at submission with the
    // server's message shown, and no job made.
    let flat = dir.path().join("flat.stl");
    std::fs::write(
        &flat,
        "solid flat\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 1 1\nvertex 2 2 2\nendloop\nendfacet\nendsolid flat\n",
    )?;
    c.find(Locator::Css("#file-input")).await?.send_keys(&flat.to_string_lossy()).await?;
    c.wait().at_most(Duration::from_secs(20)).for_element(Locator::Css("#submit-job")).await?.click().await?;
    let error = until(
        &c,
        "the submission error",
        Duration::from_secs(20),
        "return document.querySelector('#form-error')?.textContent",
    )
    .await?;
    let error = error.as_str().unwrap_or_default().to_string();
    assert!(error.contains("degenerate"), "{error}");
    let shot = c.screenshot().await?;
    keep("console-error.png", &shot)?;
    let list: Value = stack.http.get(stack.url("/v1/jobs")).bearer_auth(&token).send().await?.json().await?;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");
    // A bad value in the form: the error sits next to the field the server names.
    c.find(Locator::Css("details[data-section=\"plan\"] > summary")).await?.click().await?;
    let field = c.find(Locator::Css("[data-field=\"plan.finishing.step_over_mm\"]:is(input)")).await?;
    field.send_keys("-2").await?;
    c.find(Locator::Css("#submit-job")).await?.click().await?;
    let next_to = until(
        &c,
        "the field error",
        Duration::from_secs(20),
        "return document.querySelector('.field.invalid[data-field=\"plan.finishing.step_over_mm\"] .field-error')?.textContent",
    )
    .await?;
    assert!(next_to.as_str().unwrap_or_default().contains("positive"), "{next_to}");

    // A mesh may be made by the robot: its settings replace the scan, reconstruct and plan
    // sections (the bad plan value above is no longer sent), of execute only the dexel cell
    // stays, and the server's check of a robot setting lands next to that field.
    c.find(Locator::Css("#f-process")).await?.send_keys("robot").await?;
    let shown = c
        .execute(
            "const f = document.querySelector('#job-form');
             const vis = (s) => !f.querySelector(`details[data-section=\"${s}\"]`).hidden;
             return [vis('scan'), vis('reconstruct'), vis('plan'), vis('robot'), vis('execute'),
                     [...f.querySelectorAll('details[data-section=\"execute\"] .field')].filter(e => !e.hidden).map(e => e.dataset.field)]",
            vec![],
        )
        .await?;
    assert_eq!(shown, json!([false, false, false, true, true, ["execute.cell_mm"]]), "{shown}");
    c.find(Locator::Css("details[data-section=\"robot\"] > summary")).await?.click().await?;
    c.find(Locator::Css("[data-field=\"robot.max_tilt_deg\"]:is(input)")).await?.send_keys("95").await?;
    c.find(Locator::Css("#submit-job")).await?.click().await?;
    let next_to = until(
        &c,
        "the robot field error",
        Duration::from_secs(20),
        "return document.querySelector('.field.invalid[data-field=\"robot.max_tilt_deg\"] .field-error')?.textContent",
    )
    .await?;
    assert!(next_to.as_str().unwrap_or_default().contains("from 0 to 80"), "{next_to}");

    assert_eq!(console_errors(&c).await?, Vec::<String>::new(), "errors in the page");
    c.close().await?;
    drop(driver);
    stack.shutdown().await
}
