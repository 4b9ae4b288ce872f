//! The job-store suite, run against both backends: every case once on a fresh SQLite file and once
//! on a fresh PostgreSQL database.
//!
//! PostgreSQL: a [`scratch::ScratchDatabase`] per test, on the server at
//! `DEPTHMILL_TEST_POSTGRES_URL` (default: the trust-auth server of the development and CI machines,
//! `postgres://postgres@127.0.0.1:5432/postgres`). A missing server fails the tests: the Postgres
//! backend is part of the product, not an option of the test run.

use std::collections::HashSet;
use std::sync::Arc;

use super::*;
use crate::domain::StageOutputs;
use crate::domain::spec::{InputKind, JobInput};

fn spec(name: &str) -> JobSpec {
    JobSpec {
        name: name.into(),
        input: JobInput {
            kind: InputKind::Gcode,
            artifact: "a".repeat(64),
            pixel_mm: None,
            z_min_mm: None,
            z_max_mm: None,
            units: None,
        },
        scan: None,
        reconstruct: None,
        plan: None,
        execute: None,
        process: None,
        robot: None,
    }
}

fn new(id: &str, key: Option<&str>) -> NewJob {
    NewJob { id: id.into(), spec: spec(id), idempotency_key: key.map(Into::into), client: None, now_ms: 1 }
}

/// A database of one test; dropped (with its data) when the test ends.
enum Db {
    Sqlite(tempfile::TempDir),
    Postgres(scratch::ScratchDatabase),
}

impl Db {
    fn sqlite() -> Self {
        Db::Sqlite(tempfile::tempdir().expect("tempdir"))
    }

    async fn postgres() -> Self {
        match scratch::ScratchDatabase::create().await {
            Ok(db) => Db::Postgres(db),
            Err(e) => {
                panic!("PostgreSQL is needed for the job-store tests: {}", depthmill_common::ErrorChain(&e))
            }
        }
    }

    /// The URL a store of this database opens.
    fn url(&self) -> String {
        match self {
            Db::Sqlite(dir) => format!("sqlite://{}", dir.path().join("jobs.sqlite").display()),
            Db::Postgres(db) => db.url(),
        }
    }

    async fn store(&self) -> Arc<dyn JobStore> {
        open(&self.url()).await.expect("open store")
    }
}

/// Runs each case against both backends.
macro_rules! suite {
    ($($case:ident),* $(,)?) => {
        mod sqlite_backend {
            $(#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn $case() {
                super::$case(super::Db::sqlite()).await;
            })*
        }
        mod postgres_backend {
            $(#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn $case() {
                super::$case(super::Db::postgres().await).await;
            })*
        }
    };
}

suite!(
    leases_fence_writers_and_a_stage_is_recorded_once,
    recovery_releases_the_owner_s_jobs_and_marks_attempts_interrupted,
    idempotency_keys_and_cancel_and_pages,
    concurrent_replicas_claim_every_job_exactly_once,
    a_job_reads_back_as_it_was_written,
    tokens_are_found_by_hash_listed_and_revoked_once,
    active_jobs_are_counted_per_client,
    calibrations_are_versioned_in_order_and_the_newest_is_in_force,
    stage_diagnostics_are_kept_with_the_stage_and_read_back_in_stage_order,
);

fn result(stage: Stage) -> StageResult {
    StageResult { stage, outputs: StageOutputs::default(), started_at_ms: 1, finished_at_ms: 2 }
}

async fn leases_fence_writers_and_a_stage_is_recorded_once(db: Db) {
    let s = db.store().await;
    assert!(matches!(s.create(new("j1", None)).await.expect("create"), Created::New(_)));
    let claimed = s.claim("a", 100, 1000).await.expect("claim").expect("a job");
    assert_eq!((claimed.id.as_str(), claimed.stage), ("j1", Stage::Execute));
    // Leased: nobody else gets it until the lease expires.
    assert!(s.claim("b", 500, 1000).await.expect("claim").is_none());
    let attempt = s.begin_attempt("j1", "a", Stage::Execute, 200).await.expect("begin");
    assert_eq!(attempt, 1);
    // The lease expires; b takes over; a can no longer write.
    let taken = s.claim("b", 5000, 1000).await.expect("claim").expect("expired lease");
    assert_eq!(taken.id, "j1");
    let r = result(Stage::Execute);
    let lost = s.complete_stage("j1", "a", &r, Some(Stage::Report), 0.5, 5001).await;
    assert!(matches!(lost, Err(StoreError::LeaseLost { .. })), "{lost:?}");
    assert!(!s.renew("j1", "a", 5002, 1000).await.expect("renew").held);
    assert!(matches!(
        s.end("j1", "a", JobStatus::Failed, None, 5002).await,
        Err(StoreError::LeaseLost { .. })
    ));
    let b_attempt = s.begin_attempt("j1", "b", Stage::Execute, 5002).await.expect("begin");
    s.complete_stage("j1", "b", &r, Some(Stage::Report), 0.5, 5003).await.expect("b completes");
    // b's attempt is ok with the stage, in the same write; a's (it lost the lease) is not.
    let attempts = s.get("j1").await.expect("get").expect("job").attempts;
    let outcome = |n: u32| attempts.iter().find(|a| a.attempt == n).map(|a| a.outcome);
    assert_eq!(outcome(b_attempt), Some(AttemptOutcome::Ok), "{attempts:?}");
    assert_eq!(outcome(attempt), Some(AttemptOutcome::Running), "{attempts:?}");
    // A second record of the same stage is refused by the schema, and changes nothing.
    let again = s.complete_stage("j1", "b", &r, Some(Stage::Report), 0.9, 5004).await;
    assert!(again.is_err(), "recorded twice");
    let job = s.get("j1").await.expect("get").expect("job");
    assert_eq!(job.stage, Stage::Report);
    assert_eq!(job.stage_timings_s.len(), 1);
    assert_eq!(job.progress, 0.5, "the refused write changed nothing");
    assert_eq!(s.stage_results("j1").await.expect("results").len(), 1);
    // The last stage ends the job and releases the lease.
    s.complete_stage("j1", "b", &result(Stage::Report), None, 1.0, 5005).await.expect("report");
    let job = s.get("j1").await.expect("get").expect("job");
    assert_eq!((job.status, job.progress), (JobStatus::Succeeded, 1.0));
    assert!(s.claim("c", 1_000_000, 1000).await.expect("claim").is_none(), "a finished job is not claimed");
}

async fn recovery_releases_the_owner_s_jobs_and_marks_attempts_interrupted(db: Db) {
    let s = db.store().await;
    s.create(new("j1", None)).await.expect("create");
    s.claim("node-1", 0, 60_000).await.expect("claim").expect("job");
    s.begin_attempt("j1", "node-1", Stage::Execute, 1).await.expect("begin");
    assert_eq!(s.recover_owner("node-2", 2).await.expect("recover"), 0, "another node's lease stays");
    assert_eq!(s.recover_owner("node-1", 2).await.expect("recover"), 1);
    let job = s.get("j1").await.expect("get").expect("job");
    assert_eq!(job.attempts[0].outcome, AttemptOutcome::Interrupted);
    let again = s.claim("node-1", 3, 60_000).await.expect("claim").expect("released");
    assert_eq!(again.stage, Stage::Execute);
    assert_eq!(s.begin_attempt("j1", "node-1", Stage::Execute, 4).await.expect("begin"), 2);
}

async fn idempotency_keys_and_cancel_and_pages(db: Db) {
    let s = db.store().await;
    assert!(matches!(s.create(new("j1", Some("k"))).await.expect("create"), Created::New(_)));
    let mut same = new("j2", Some("k"));
    same.spec = spec("j1");
    match s.create(same).await.expect("same request") {
        Created::Existing(job) => assert_eq!(job.id, "j1"),
        Created::New(_) => panic!("a second job for the same key"),
    }
    assert!(matches!(s.create(new("j3", Some("k"))).await, Err(StoreError::IdempotencyConflict { .. })));
    for i in 4..9 {
        s.create(new(&format!("j{i}"), None)).await.expect("create");
    }
    let job = s.request_cancel("j4", 10).await.expect("cancel").expect("job");
    assert_eq!(job.status, JobStatus::Cancelled, "a queued job is cancelled at once");
    assert_eq!(job.error.as_ref().map(|e| e.code.as_str()), Some("cancelled"));
    assert!(s.request_cancel("nope", 10).await.expect("cancel").is_none());
    // A running job is only asked to stop; its worker sees it on renewal.
    s.claim("w", 20, 1000).await.expect("claim").expect("j1");
    let running = s.request_cancel("j1", 21).await.expect("cancel").expect("job");
    assert_eq!((running.status, running.cancel_requested), (JobStatus::Queued, true));
    assert!(s.renew("j1", "w", 22, 1000).await.expect("renew").cancel_requested);
    let mut seen = Vec::new();
    let mut cursor = None;
    loop {
        let page = s.list(Some(JobStatus::Queued), 2, cursor).await.expect("list");
        seen.extend(page.jobs.into_iter().map(|j| j.id));
        match page.next_cursor {
            Some(c) => cursor = Some(c),
            None => break,
        }
    }
    assert_eq!(seen, ["j8", "j7", "j6", "j5", "j1"]);
    let all = s.list(None, 1000, None).await.expect("list");
    assert_eq!(all.jobs.len(), 6);
    assert!(all.next_cursor.is_none());
}

/// Queued and running jobs count against their client; ended ones and other clients' do not.
async fn active_jobs_are_counted_per_client(db: Db) {
    let s = db.store().await;
    let of = |id: &str, client: Option<&str>| NewJob { client: client.map(Into::into), ..new(id, None) };
    for i in 0..3 {
        s.create(of(&format!("a{i}"), Some("token:tok_a"))).await.expect("create");
    }
    s.create(of("b0", Some("addr:10.0.0.2"))).await.expect("create");
    s.create(of("n0", None)).await.expect("create");
    s.create(NewJob { idempotency_key: Some("key-a".into()), ..of("a3", Some("token:tok_a")) })
        .await
        .expect("create");
    assert_eq!(s.active_jobs_of("token:tok_a", 100).await.expect("count"), 4);
    assert_eq!(s.active_jobs_of("addr:10.0.0.2", 100).await.expect("count"), 1);
    assert_eq!(s.active_jobs_of("token:tok_other", 100).await.expect("count"), 0);
    // Running still counts; cancelled (and any other end) does not.
    let claimed = s.claim("w", 10, 1000).await.expect("claim").expect("a job");
    assert_eq!(claimed.id, "a0", "the oldest job first");
    assert_eq!(s.active_jobs_of("token:tok_a", 100).await.expect("count"), 4);
    s.request_cancel("a1", 11).await.expect("cancel").expect("job");
    s.end("a0", "w", JobStatus::Succeeded, None, 12).await.expect("end");
    assert_eq!(s.active_jobs_of("token:tok_a", 100).await.expect("count"), 2);
    // Counted up to the limit asked about.
    assert_eq!(s.active_jobs_of("token:tok_a", 1).await.expect("count"), 1);
    assert!(s.key_exists("key-a").await.expect("key"));
    assert!(!s.key_exists("key-b").await.expect("key"));
}

/// Three replicas (three stores on one database), each with several workers claiming at once: every
/// job is claimed by exactly one of them, none is left behind.
async fn concurrent_replicas_claim_every_job_exactly_once(db: Db) {
    const JOBS: usize = 60;
    let replicas = [db.store().await, db.store().await, db.store().await];
    for i in 0..JOBS {
        replicas[i % 3].create(new(&format!("j{i:03}"), None)).await.expect("create");
    }
    let mut tasks = tokio::task::JoinSet::new();
    for (r, store) in replicas.iter().enumerate() {
        for w in 0..3 {
            let store = store.clone();
            tasks.spawn(async move {
                let owner = format!("replica-{r}-worker-{w}");
                let mut mine = Vec::new();
                // A long lease: nothing expires during the test, so a second claim would be a bug.
                while let Some(job) = store.claim(&owner, 1_000, 3_600_000).await.expect("claim") {
                    store.begin_attempt(&job.id, &owner, job.stage, 1_001).await.expect("fenced by my lease");
                    mine.push(job.id);
                }
                mine
            });
        }
    }
    let mut seen = HashSet::new();
    let mut total = 0;
    while let Some(mine) = tasks.join_next().await {
        for id in mine.expect("worker") {
            total += 1;
            assert!(seen.insert(id.clone()), "{id} claimed twice");
        }
    }
    assert_eq!((total, seen.len()), (JOBS, JOBS));
    for id in &seen {
        let job = replicas[0].get(id).await.expect("get").expect("job");
        assert_eq!(job.attempts.len(), 1, "{id}: {:?}", job.attempts);
    }
}

async fn a_job_reads_back_as_it_was_written(db: Db) {
    let s = db.store().await;
    let mut n = new("j1", Some("key-1"));
    n.spec.name = "bracket, 2nd \"op\" ✓".into();
    let Created::New(created) = s.create(n).await.expect("create") else { panic!("new job") };
    let read = s.get("j1").await.expect("get").expect("job");
    assert_eq!(serde_json::to_value(&created).ok(), serde_json::to_value(&read).ok());
    s.claim("w", 10, 1000).await.expect("claim").expect("job");
    let attempt = s.begin_attempt("j1", "w", Stage::Execute, 11).await.expect("begin");
    s.finish_attempt(
        "j1",
        Stage::Execute,
        attempt,
        AttemptOutcome::Failed,
        Some(("unavailable", "down")),
        15,
    )
    .await
    .expect("finish");
    s.set_progress("j1", "w", 0.25, 16).await.expect("progress");
    let error =
        JobError { code: "unavailable".into(), message: "machine down".into(), stage: Stage::Execute };
    s.end("j1", "w", JobStatus::Failed, Some(&error), 17).await.expect("end");
    let job = s.get("j1").await.expect("get").expect("job");
    assert_eq!(job.status, JobStatus::Failed);
    assert_eq!(job.error.as_ref().map(|e| (e.code.as_str(), e.stage)), Some(("unavailable", Stage::Execute)));
    assert_eq!(job.progress, 0.25);
    assert_eq!(job.updated_at_ms, 17);
    let a = &job.attempts[0];
    assert_eq!(
        (a.outcome, a.finished_at_ms, a.error_message.as_deref()),
        (AttemptOutcome::Failed, Some(15), Some("down"))
    );
    assert_eq!(job.stage_timings_s.get("execute"), Some(&0.004), "a failed stage shows its attempts' time");
    s.ping().await.expect("ping");
}

async fn tokens_are_found_by_hash_listed_and_revoked_once(db: Db) {
    let s = db.store().await;
    let issued = crate::auth::issue(&*s, "cell 3", "read,submit", Some(60.0), 1_000).await.expect("issue");
    assert!(issued.token.starts_with("dmt_") && issued.token.len() == 68, "{}", issued.token);
    assert_eq!(issued.record.scopes, "read submit");
    assert_eq!(issued.record.expires_at_ms, Some(61_000));
    let hash = crate::auth::secret_hash(&issued.token);
    assert_eq!(s.token_by_secret(&hash).await.expect("lookup").as_ref(), Some(&issued.record));
    assert!(s.token_by_secret(&crate::auth::secret_hash("dmt_other")).await.expect("lookup").is_none());
    // The same secret cannot be stored twice.
    assert!(
        s.create_token(&TokenRecord { id: "tok_x".into(), ..issued.record.clone() }, &hash).await.is_err()
    );
    let other = crate::auth::issue(&*s, "dashboard", "read", None, 2_000).await.expect("issue");
    let listed = s.list_tokens().await.expect("list");
    assert_eq!(listed, [issued.record.clone(), other.record.clone()]);
    assert!(s.revoke_token(&issued.record.id, 3_000).await.expect("revoke"));
    assert!(!s.revoke_token(&issued.record.id, 4_000).await.expect("revoke"), "revoked once");
    assert!(!s.revoke_token("tok_none", 4_000).await.expect("revoke"));
    let found = s.token_by_secret(&hash).await.expect("lookup").expect("still listed");
    assert_eq!(found.revoked_at_ms, Some(3_000));
    for bad in [("", "read"), ("x", "write"), ("x", "")] {
        assert!(crate::auth::issue(&*s, bad.0, bad.1, None, 5_000).await.is_err(), "{bad:?}");
    }
    assert_eq!(s.list_tokens().await.expect("list").len(), 2, "refused tokens stored nothing");
}

#[tokio::test]
async fn a_url_names_its_backend_and_a_bad_one_is_refused() {
    for url in ["mysql://root@localhost/db", "jobs.sqlite", "sqlite://", "redis://x:secret@h/0"] {
        match open(url).await {
            Err(e @ StoreError::BadUrl { .. }) => assert!(!e.to_string().contains("secret"), "{e}"),
            Err(e) => panic!("{url}: {e}"),
            Ok(_) => panic!("{url} opened"),
        }
    }
    assert_eq!(redact("postgres://u:pw@h:5432/db"), "postgres://u:***@h:5432/db");
    assert_eq!(redact("postgres://u@h/db"), "postgres://u@h/db");
    assert_eq!(redact("sqlite://data/jobs.sqlite"), "sqlite://data/jobs.sqlite");
}

#[tokio::test]
async fn an_unreachable_database_is_unavailable_not_internal() {
    // Nothing listens on port 1 of loopback.
    let Err(e) = open("postgres://postgres@127.0.0.1:1/depthmill").await else { panic!("connected") };
    assert!(e.is_unavailable(), "{e:?}");
}

async fn calibrations_are_versioned_in_order_and_the_newest_is_in_force(db: Db) {
    let s = db.store().await;
    assert!(s.latest_calibration().await.expect("latest").is_none());
    let rec = |id: &str, at: i64| super::CalibrationRecord {
        id: id.into(),
        version: 99,
        created_at_ms: at,
        trigger_kind: "api".into(),
        calibration_json: format!("{{\"id\":\"{id}\"}}"),
        report_json: "{}".into(),
    };
    let a = s.create_calibration(&rec("cal_a", 10)).await.expect("first");
    assert_eq!(a.version, 1, "the version is the store's, not the caller's");
    let b = s.create_calibration(&rec("cal_b", 20)).await.expect("second");
    assert_eq!(b.version, 2);
    assert_eq!(s.latest_calibration().await.expect("latest"), Some(b.clone()));
    assert_eq!(s.get_calibration("cal_a").await.expect("get"), Some(a.clone()));
    assert!(s.get_calibration("cal_none").await.expect("get").is_none());
    assert_eq!(s.list_calibrations(10).await.expect("list"), [b.clone(), a.clone()]);
    assert_eq!(s.list_calibrations(1).await.expect("list"), [b]);
    // The same id twice is refused and changes nothing.
    assert!(s.create_calibration(&rec("cal_a", 30)).await.is_err());
    assert_eq!(s.list_calibrations(10).await.expect("list").len(), 2);
}

async fn stage_diagnostics_are_kept_with_the_stage_and_read_back_in_stage_order(db: Db) {
    let s = db.store().await;
    s.create(new("j1", None)).await.expect("create");
    s.claim("w", 10, 1000).await.expect("claim").expect("job");
    let mut execute = result(Stage::Execute);
    execute.outputs.set_diagnostics([
        ("machine".to_string(), "line 12: feed 9000 mm/min clamped to 6000 \"F\" ✓".to_string()),
        ("material_left".to_string(), "face 1: 3.5 mm² around (1.0, -2.0) mm".to_string()),
    ]);
    s.begin_attempt("j1", "w", Stage::Execute, 11).await.expect("begin");
    s.complete_stage("j1", "w", &execute, Some(Stage::Report), 0.5, 12).await.expect("execute");
    let mut report = result(Stage::Report);
    report.outputs.set_diagnostics([("report".to_string(), "done".to_string())]);
    s.begin_attempt("j1", "w", Stage::Report, 13).await.expect("begin");
    s.complete_stage("j1", "w", &report, None, 1.0, 14).await.expect("report");
    let job = s.get("j1").await.expect("get").expect("job");
    let got: Vec<(Stage, &str, &str)> =
        job.diagnostics.iter().map(|d| (d.stage, d.code.as_str(), d.message.as_str())).collect();
    assert_eq!(
        got,
        [
            (Stage::Execute, "machine", "line 12: feed 9000 mm/min clamped to 6000 \"F\" ✓"),
            (Stage::Execute, "material_left", "face 1: 3.5 mm² around (1.0, -2.0) mm"),
            (Stage::Report, "report", "done"),
        ]
    );
    // Listed jobs carry them too.
    let page = s.list(None, 10, None).await.expect("list");
    assert_eq!(page.jobs.first().map(|j| j.diagnostics.len()), Some(3));
}
