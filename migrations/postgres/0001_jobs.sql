-- Jobs, their stage results and every attempt at a stage (PostgreSQL; the same model as
-- migrations/sqlite). Times are milliseconds since the Unix epoch.

CREATE TABLE jobs (
    seq              BIGINT  GENERATED ALWAYS AS IDENTITY PRIMARY KEY, -- submission order, the list cursor
    id               TEXT    NOT NULL UNIQUE,                          -- UUIDv7
    name             TEXT    NOT NULL,
    spec             TEXT    NOT NULL,                                 -- the job request, JSON
    first_stage      TEXT    NOT NULL,
    status           TEXT    NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    stage            TEXT    NOT NULL CHECK (stage IN ('scan', 'reconstruct', 'plan', 'execute', 'report')),
    progress         DOUBLE PRECISION NOT NULL DEFAULT 0,
    error_code       TEXT,
    error_message    TEXT,
    error_stage      TEXT,
    idempotency_key  TEXT    UNIQUE,
    cancel_requested BOOLEAN NOT NULL DEFAULT FALSE,
    lease_owner      TEXT,                                             -- the replica running it
    lease_expires_ms BIGINT,
    created_at_ms    BIGINT  NOT NULL,
    updated_at_ms    BIGINT  NOT NULL
);

CREATE INDEX jobs_runnable ON jobs (seq) WHERE status IN ('queued', 'running');
CREATE INDEX jobs_by_status ON jobs (status, seq);
CREATE INDEX jobs_by_owner ON jobs (lease_owner) WHERE lease_owner IS NOT NULL;

-- A stage's result is recorded once: the primary key makes a second record impossible.
CREATE TABLE stage_results (
    job_id         TEXT    NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    stage          TEXT    NOT NULL,
    outputs        TEXT    NOT NULL,                                   -- StageOutputs, JSON
    started_at_ms  BIGINT  NOT NULL,
    finished_at_ms BIGINT  NOT NULL,
    PRIMARY KEY (job_id, stage)
);

CREATE TABLE attempts (
    id             BIGINT  GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    job_id         TEXT    NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    stage          TEXT    NOT NULL,
    attempt        BIGINT  NOT NULL,
    owner          TEXT    NOT NULL,
    started_at_ms  BIGINT  NOT NULL,
    finished_at_ms BIGINT,
    outcome        TEXT    NOT NULL,
    error_code     TEXT,
    error_message  TEXT,
    UNIQUE (job_id, stage, attempt)
);

CREATE INDEX attempts_by_job ON attempts (job_id, id);
CREATE INDEX attempts_running ON attempts (owner) WHERE outcome = 'running';
