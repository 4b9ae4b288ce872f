-- Jobs, their stage results and every attempt at a stage.
-- Times are milliseconds since the Unix epoch.

CREATE TABLE jobs (
    seq              INTEGER PRIMARY KEY AUTOINCREMENT,  -- submission order, the list cursor
    id               TEXT    NOT NULL UNIQUE,            -- UUIDv7
    name             TEXT    NOT NULL,
    spec             TEXT    NOT NULL,                   -- the job request, JSON
    first_stage      TEXT    NOT NULL,
    status           TEXT    NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    stage            TEXT    NOT NULL CHECK (stage IN ('scan', 'reconstruct', 'plan', 'execute', 'report')),
    progress         REAL    NOT NULL DEFAULT 0,
    error_code       TEXT,
    error_message    TEXT,
    error_stage      TEXT,
    idempotency_key  TEXT    UNIQUE,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    lease_owner      TEXT,                               -- the worker (node) running it
    lease_expires_ms INTEGER,
    created_at_ms    INTEGER NOT NULL,
    updated_at_ms    INTEGER NOT NULL
);

CREATE INDEX jobs_runnable ON jobs (status, seq) WHERE status IN ('queued', 'running');
CREATE INDEX jobs_by_status ON jobs (status, seq);

-- A stage's result is recorded once: the primary key makes a second record impossible.
CREATE TABLE stage_results (
    job_id         TEXT    NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    stage          TEXT    NOT NULL,
    outputs        TEXT    NOT NULL,                     -- StageOutputs, JSON
    started_at_ms  INTEGER NOT NULL,
    finished_at_ms INTEGER NOT NULL,
    PRIMARY KEY (job_id, stage)
);

CREATE TABLE attempts (
    id             INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id         TEXT    NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    stage          TEXT    NOT NULL,
    attempt        INTEGER NOT NULL,
    owner          TEXT    NOT NULL,
    started_at_ms  INTEGER NOT NULL,
    finished_at_ms INTEGER,
    outcome        TEXT    NOT NULL,
    error_code     TEXT,
    error_message  TEXT,
    UNIQUE (job_id, stage, attempt)
);

CREATE INDEX attempts_by_job ON attempts (job_id, id);
