//! The `depthmill` command line as a process (this test binary in the `Cli` child role, which runs
//! exactly what the binary runs): output into a pipe closed early ends quietly with success, a
//! server that is down or answers garbage gets one line on standard error and exit code 1.

use std::io::{BufRead as _, BufReader, Read as _};
use std::process::{Command, Stdio};

use anyhow::Context as _;
use depthmill_tests::TestStack;
use serde_json::json;

use crate::children::Role;

/// Runs the command line `args` in a child process; (exit code, stdout, stderr).
fn depthmill(args: &[&str]) -> anyhow::Result<(i32, String, String)> {
    let mut argv = vec!["depthmill".to_string()];
    argv.extend(args.iter().map(|a| a.to_string()));
    let role = serde_json::to_string(&Role::Cli { args: argv, after_stdin: false })?;
    let out = Command::new(std::env::current_exe()?)
        .args(["--ignored", "--exact", "children::child_process", "--nocapture", "--test-threads=1"])
        .env("DEPTHMILL_E2E_CHILD", role)
        .env_remove("DEPTHMILL_URL")
        .env_remove("DEPTHMILL_TOKEN")
        .stdin(Stdio::null())
        .output()?;
    Ok((
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn output_into_a_closed_pipe_ends_quietly() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-gcode", b"%\nG21 G90\nG0 X1\nM30\n%\n".to_vec()).await?;
    let (status, created) = stack
        .post_job(&json!({"input": {"kind": "gcode", "artifact": sha}, "execute": {"adaptive": "off"}}), None)
        .await?;
    anyhow::ensure!(status == 201, "{created}");
    let id = created["id"].as_str().context("id")?.to_string();
    let url = stack.rest_url.clone();

    // `depthmill status ID --json --url URL | head -0`: the reader is gone before the first write.
    let argv: Vec<String> =
        ["depthmill", "status", &id, "--json", "--url", &url].iter().map(|s| s.to_string()).collect();
    let role = serde_json::to_string(&Role::Cli { args: argv, after_stdin: true })?;
    let output = tokio::task::spawn_blocking(move || -> anyhow::Result<(i32, String)> {
        // Terse output (`-q`): the harness prints nothing between "running 1 test" and the end
        // of the test, which this process never reaches.
        let mut child = Command::new(std::env::current_exe()?)
            .args([
                "--ignored",
                "--exact",
                "children::child_process",
                "--nocapture",
                "--test-threads=1",
                "-q",
            ])
            .env("DEPTHMILL_E2E_CHILD", role)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        // The test harness's own lines (up to "running 1 test"), then the pipe closes.
        let mut stdout = BufReader::new(child.stdout.take().context("stdout")?);
        let mut line = String::new();
        while stdout.read_line(&mut line)? > 0 && line.trim() != "running 1 test" {
            line.clear();
        }
        drop(stdout);
        drop(child.stdin.take());
        let mut stderr = String::new();
        child.stderr.take().context("stderr")?.read_to_string(&mut stderr)?;
        let status = child.wait()?;
        Ok((status.code().unwrap_or(-1), stderr))
    })
    .await??;
    let (code, stderr) = output;
    assert_eq!(code, 0, "a closed pipe is not an error: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.trim().is_empty(), "nothing on standard error: {stderr}");

    // The same verb into an open pipe prints the job.
    let (code, out, err) = depthmill(&["status", &id, "--json", "--url", &url])?;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains(&id), "{out}");
    stack.shutdown().await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_is_down_or_answers_garbage_gets_one_line_and_exit_1() -> anyhow::Result<()> {
    // Down: nothing listens on the port.
    let port = crate::children::free_addr()?.port();
    let down = format!("http://127.0.0.1:{port}");
    let (code, out, err) =
        tokio::task::spawn_blocking(move || depthmill(&["status", "some-job", "--url", &down])).await??;
    assert_eq!(code, 1, "{out}{err}");
    let line = err.trim();
    assert!(line.starts_with("depthmill: ") && !line.contains('\n'), "one line: {err:?}");
    assert!(!err.contains("panicked"), "{err}");

    // Garbage: an HTTP server answering 200 with something that is not the API's JSON.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let garbage = format!("http://{}", listener.local_addr()?);
    tokio::spawn(async move {
        use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
        while let Ok((mut socket, _)) = listener.accept().await {
            let mut buf = [0u8; 4096];
            let _ = socket.read(&mut buf).await;
            let _ = socket
                .write_all(b"HTTP/1.1 200 OK\r\ncontent-type: text/html\r\ncontent-length: 14\r\nconnection: close\r\n\r\n<html>hi</html")
                .await;
        }
    });
    let dir = tempfile::tempdir()?;
    let into = dir.path().join("fetched").display().to_string();
    for verb in [vec!["status", "some-job"], vec!["fetch", "some-job", "-o", into.as_str()]] {
        let mut args: Vec<String> = verb.iter().map(|s| s.to_string()).collect();
        args.extend(["--url".to_string(), garbage.clone()]);
        let (code, out, err) = tokio::task::spawn_blocking(move || {
            let refs: Vec<&str> = args.iter().map(String::as_str).collect();
            depthmill(&refs)
        })
        .await??;
        assert_eq!(code, 1, "{verb:?}: {out}{err}");
        let line = err.trim();
        assert!(line.starts_with("depthmill: ") && !line.contains('\n'), "{verb:?}: one line: {err:?}");
        assert!(!err.contains("panicked"), "{err}");
    }
    Ok(())
}
