//! The orchestrator: persisted scan-to-part jobs.
//!
//! A job starts at the stage its input allows (mesh -> scan, point cloud -> reconstruct, depth map
//! -> plan, G-code -> execute) and runs `scan -> reconstruct -> plan -> execute -> report`. Jobs
//! live in SQLite (WAL) or PostgreSQL; a worker advances each job by calling the stage's service over gRPC, with
//! deadlines, retries with backoff for transient errors, every attempt recorded, and resumption
//! after a crash. REST (axum) and gRPC (tonic) expose the same operations over one [`app::App`].
//!
//! # Layout
//! - [`domain`]: the job model and request validation (pure); the `scan` and `reconstruct`
//!   sections are checked by the services that own them, through [`stages::StageRunner::check_params`].
//! - [`store`]: the [`store::JobStore`] trait, its SQLite (embedded default) and PostgreSQL
//!   (replicas) implementations.
//! - [`stages`]: the [`stages::StageRunner`] port and its gRPC adapter.
//! - [`worker`]: claims jobs and runs them stage by stage.
//! - [`app`]: operations shared by both APIs; [`http`] (REST + OpenAPI) and `grpc` adapt it.
//! - [`events`]: change notifications for watchers and idle workers.
//! - `convert`: job model <-> wire types.
//!
//! The report stage renders with `depthmill-report`. This crate imports no stage service's code:
//! it knows the stages only by their gRPC contracts (`depthmill-proto`).

#[cfg(feature = "service")]
pub mod app;
#[cfg(feature = "service")]
pub mod auth;
#[cfg(feature = "service")]
mod balance;
#[cfg(feature = "service")]
mod convert;
pub mod domain;
#[cfg(feature = "service")]
pub mod events;
#[cfg(feature = "service")]
mod grpc;
#[cfg(feature = "service")]
pub mod http;
#[cfg(feature = "service")]
mod service;
#[cfg(feature = "service")]
pub mod stages;
#[cfg(feature = "service")]
pub mod store;
#[cfg(feature = "service")]
pub mod worker;

#[cfg(feature = "service")]
pub use service::*;
