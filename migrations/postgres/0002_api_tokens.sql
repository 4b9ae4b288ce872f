-- Bearer tokens of the REST and gRPC APIs. The secret itself is never stored: only its SHA-256.
CREATE TABLE api_tokens (
    id            TEXT    PRIMARY KEY,          -- public handle (tok_...), for listing and revoking
    name          TEXT    NOT NULL,             -- who or what holds it
    secret_sha256 TEXT    NOT NULL UNIQUE,      -- hex SHA-256 of the whole token string
    scopes        TEXT    NOT NULL,             -- space-separated: read, submit, admin
    created_at_ms BIGINT  NOT NULL,
    expires_at_ms BIGINT,                       -- NULL: does not expire
    revoked_at_ms BIGINT                        -- NULL: not revoked
);
