//! gRPC contracts of depthmill, compiled from `proto/depthmill/**/*.proto` without a system `protoc`.
//!
//! # Layout
//! - [`types::v1`]: artifact references, stage context, progress (shared by every service).
//! - [`scanning::v1`], [`reconstruction::v1`], [`cam::v1`], [`machine::v1`]: the stage services.
//! - [`orchestrator::v1`]: jobs and artifact upload/download.
//! - [`error`]: [`ErrorCode`], the one mapping of error kinds to gRPC codes and HTTP statuses.
//! - [`convert`]: conversions between wire types and `depthmill-geometry` types.
//! - [`FILE_DESCRIPTOR_SET`]: the compiled descriptors, served by gRPC reflection.

pub mod convert;
pub mod error;

pub use error::ErrorCode;

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod types {
    pub mod v1 {
        tonic::include_proto!("depthmill.types.v1");
    }
}

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod scanning {
    pub mod v1 {
        tonic::include_proto!("depthmill.scanning.v1");
    }
}

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod reconstruction {
    pub mod v1 {
        tonic::include_proto!("depthmill.reconstruction.v1");
    }
}

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod cam {
    pub mod v1 {
        tonic::include_proto!("depthmill.cam.v1");
    }
}

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod machine {
    pub mod v1 {
        tonic::include_proto!("depthmill.machine.v1");
    }
}

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod orchestrator {
    pub mod v1 {
        tonic::include_proto!("depthmill.orchestrator.v1");
    }
}

/// Encoded `FileDescriptorSet` of every depthmill proto, for the gRPC reflection service.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("depthmill_descriptor");
