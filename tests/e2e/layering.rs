//! The dependency rules of ARCHITECTURE.md, checked from `cargo metadata` and the sources so they
//! cannot break silently:
//! - a stage service (scanning, reconstruction, cam, machine) imports no other stage service;
//! - the orchestrator imports no stage service (it knows them by their gRPC contracts);
//! - the bottom crates import nothing above them: `depthmill-geometry` no depthmill crate,
//!   `depthmill-proto` only geometry, `depthmill-report` only geometry, `depthmill-common` only
//!   proto and geometry;
//! - pure code (geometry, report, every `services/*/src/domain/`) uses no tokio, tonic, sqlx or
//!   axum, and no `depthmill-proto` or `depthmill-common`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const STAGE_SERVICES: [&str; 4] =
    ["depthmill-scanning", "depthmill-reconstruction", "depthmill-cam", "depthmill-machine"];

/// What a crate may depend on among the depthmill crates (every kind: normal, dev, build).
fn allowed(krate: &str) -> Option<&'static [&'static str]> {
    Some(match krate {
        "depthmill-geometry" => &[],
        "depthmill-proto" => &["depthmill-geometry"],
        "depthmill-report" => &["depthmill-geometry"],
        "depthmill-common" => &["depthmill-proto", "depthmill-geometry"],
        "depthmill-orchestrator" => {
            &["depthmill-proto", "depthmill-common", "depthmill-geometry", "depthmill-report"]
        }
        "depthmill-scanning" | "depthmill-reconstruction" | "depthmill-cam" => {
            &["depthmill-proto", "depthmill-common", "depthmill-geometry"]
        }
        // The machine draws its telemetry chart with the report's plot module.
        "depthmill-machine" => {
            &["depthmill-proto", "depthmill-common", "depthmill-geometry", "depthmill-report"]
        }
        // The binary and the test harness assemble everything.
        "depthmill-cli" | "depthmill-tests" => return None,
        _ => &[],
    })
}

/// Crates with no I/O framework at all.
const PURE_CRATES: [&str; 2] = ["depthmill-geometry", "depthmill-report"];
const FRAMEWORKS: [&str; 4] = ["tokio", "tonic", "sqlx", "axum"];

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().map(Path::to_path_buf).unwrap_or_default()
}

/// `package name -> names of its dependencies (all kinds)` from `cargo metadata --no-deps`.
fn dependency_graph() -> anyhow::Result<BTreeMap<String, BTreeSet<String>>> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--no-deps", "--offline"])
        .current_dir(workspace_root())
        .output()?;
    anyhow::ensure!(out.status.success(), "cargo metadata failed: {}", String::from_utf8_lossy(&out.stderr));
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    let mut graph = BTreeMap::new();
    for p in meta["packages"].as_array().into_iter().flatten() {
        let name = p["name"].as_str().unwrap_or_default().to_string();
        let deps = p["dependencies"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|d| d["name"].as_str().map(str::to_string))
            .collect();
        graph.insert(name, deps);
    }
    Ok(graph)
}

#[test]
fn crates_depend_only_downwards() -> anyhow::Result<()> {
    let graph = dependency_graph()?;
    for krate in
        STAGE_SERVICES.iter().chain(&["depthmill-orchestrator", "depthmill-geometry", "depthmill-report"])
    {
        anyhow::ensure!(
            graph.contains_key(*krate),
            "{krate} is not in the workspace any more: update this test"
        );
    }
    let mut broken = Vec::new();
    for (krate, deps) in &graph {
        let Some(ok) = allowed(krate) else { continue };
        for dep in deps.iter().filter(|d| d.starts_with("depthmill-")) {
            if !ok.contains(&dep.as_str()) {
                broken.push(format!("{krate} depends on {dep}"));
            }
        }
        if PURE_CRATES.contains(&krate.as_str()) {
            for dep in deps.iter().filter(|d| FRAMEWORKS.contains(&d.as_str())) {
                broken.push(format!("{krate} depends on {dep}, but it is pure"));
            }
        }
    }
    anyhow::ensure!(broken.is_empty(), "dependency rules broken (ARCHITECTURE.md):\n{}", broken.join("\n"));
    Ok(())
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let path = entry?.path();
        if path.is_dir() {
            rust_files(&path, out)?;
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
    Ok(())
}

/// The code of a line: what precedes a `//` comment (string literals are not special-cased;
/// none of the patterns appear in one).
fn code_of(line: &str) -> &str {
    line.find("//").map_or(line, |i| &line[..i])
}

/// A use of `name` as a path root: `name::` or `use name`.
fn uses(code: &str, name: &str) -> bool {
    let bytes = code.as_bytes();
    code.match_indices(name).any(|(i, _)| {
        let before = if i == 0 { b' ' } else { bytes[i - 1] };
        let after = &code[i + name.len()..];
        !(before.is_ascii_alphanumeric() || before == b'_')
            && (after.starts_with("::") || (code[..i].trim_end().ends_with("use") && !after.starts_with('_')))
    })
}

#[test]
fn pure_code_uses_no_io_framework() -> anyhow::Result<()> {
    let root = workspace_root();
    let mut dirs = vec![root.join("services/geometry/src"), root.join("services/report/src")];
    for entry in std::fs::read_dir(root.join("services"))? {
        let domain = entry?.path().join("src/domain");
        if domain.is_dir() {
            dirs.push(domain);
        }
    }
    anyhow::ensure!(dirs.len() >= 7, "expected geometry, report and five domain folders, found {dirs:?}");
    let forbidden = ["tokio", "tonic", "sqlx", "axum", "depthmill_proto", "depthmill_common"];
    let mut broken = Vec::new();
    for dir in &dirs {
        let mut files = Vec::new();
        rust_files(dir, &mut files)?;
        for file in files {
            let text = std::fs::read_to_string(&file)?;
            for (n, line) in text.lines().enumerate() {
                let code = code_of(line);
                for name in forbidden.iter().filter(|name| uses(code, name)) {
                    let shown = file.strip_prefix(&root).unwrap_or(&file).display().to_string();
                    broken.push(format!("{shown}:{}: uses {name}: {}", n + 1, line.trim()));
                }
            }
        }
    }
    anyhow::ensure!(
        broken.is_empty(),
        "pure code uses an I/O framework (ARCHITECTURE.md):\n{}",
        broken.join("\n")
    );
    Ok(())
}

#[test]
fn the_source_check_sees_what_it_looks_for() {
    assert!(uses("use tokio::sync::mpsc;", "tokio"));
    assert!(uses("    let x = tonic::Status::ok(\"\");", "tonic"));
    assert!(uses("use sqlx;", "sqlx"));
    assert!(uses("fn f() -> depthmill_proto::ErrorCode {", "depthmill_proto"));
    assert!(!uses(code_of("// tokio::spawn is not used here"), "tokio"));
    assert!(!uses("let my_tokio::x = 1;", "tokio"));
    assert!(!uses("use tokio_util as t;", "tokio"));
    assert!(!uses("let axum_like = 3;", "axum"));
}
