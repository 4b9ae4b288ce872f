//! The job model: what a job asks for ([`spec`]), where it is ([`Stage`], [`JobStatus`]) and what
//! its stages produced ([`StageOutputs`]). Pure: no I/O, no tokio, no proto types.

pub mod job;
pub mod spec;

pub use job::{
    AttemptOutcome, AttemptRecord, Job, JobDiagnostic, JobError, JobMetrics, JobStatus, Stage,
    StageDiagnostic, StageOutputs, StageResult,
};
pub use spec::{InputKind, JobSpec, JsonError, SpecError};
