-- Calibrations of the scanning cell, versioned: the newest is in force; scan jobs record which
-- one placed their points.
CREATE TABLE calibrations (
    id               TEXT    PRIMARY KEY,       -- public handle (cal_...)
    version          INTEGER NOT NULL UNIQUE,    -- 1, 2, ... in the order they were made
    created_at_ms    INTEGER NOT NULL,
    trigger_kind     TEXT    NOT NULL,          -- api (asked for) or auto (before a scan, none in force)
    calibration_json TEXT    NOT NULL,          -- the parameters (table model, scanner mount)
    report_json      TEXT    NOT NULL           -- residuals, registration before and after, options
);
