-- Who submitted each job: the API token's id (`token:tok_...`) or, when tokens are not required,
-- the client's address (`addr:127.0.0.1`). The limit on active jobs per client counts by it.
ALTER TABLE jobs ADD COLUMN client TEXT;

CREATE INDEX jobs_active_by_client ON jobs (client) WHERE status IN ('queued', 'running');
