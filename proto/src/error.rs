//! Error kinds shared by the gRPC and HTTP edges.
//!
//! Domain errors (`thiserror` enums in each service) map to an [`ErrorCode`] in their adapter;
//! this module is the one place that knows which gRPC code and HTTP status each kind becomes,
//! so REST clients and gRPC clients see the same classification.

use tonic::codegen::http::StatusCode;

/// What went wrong, as a client should understand it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorCode {
    /// The request is malformed or names a value out of range. Retrying the same request fails again.
    InvalidArgument,
    /// The named job, artifact or route does not exist.
    NotFound,
    /// The request conflicts with the current state (e.g. an idempotency key reused with a different body).
    Conflict,
    /// The body is larger than the configured limit.
    PayloadTooLarge,
    /// The client already has as many jobs queued or running as it may; retry when one ends.
    QuotaExceeded,
    /// The body's media type is not accepted, or its bytes are not of the declared type.
    UnsupportedMediaType,
    /// The service needed for a stage does not provide it.
    StageNotAvailable,
    /// No credentials, or credentials the server does not accept (unknown, expired, revoked).
    Unauthenticated,
    /// The credentials are valid but do not allow this operation.
    PermissionDenied,
    /// A dependency is down or overloaded; retrying later may work.
    Unavailable,
    /// A deadline passed before the operation finished.
    DeadlineExceeded,
    /// The operation was cancelled.
    Cancelled,
    /// A bug or an I/O failure on the server.
    Internal,
}

impl ErrorCode {
    /// The wire name used in REST error bodies and job errors (`invalid_argument`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::InvalidArgument => "invalid_argument",
            Self::NotFound => "not_found",
            Self::Conflict => "conflict",
            Self::PayloadTooLarge => "payload_too_large",
            Self::QuotaExceeded => "quota_exceeded",
            Self::UnsupportedMediaType => "unsupported_media_type",
            Self::StageNotAvailable => "stage_not_available",
            Self::Unauthenticated => "unauthenticated",
            Self::PermissionDenied => "permission_denied",
            Self::Unavailable => "unavailable",
            Self::DeadlineExceeded => "deadline_exceeded",
            Self::Cancelled => "cancelled",
            Self::Internal => "internal",
        }
    }

    /// The gRPC status code for this kind.
    pub fn grpc(self) -> tonic::Code {
        match self {
            Self::InvalidArgument => tonic::Code::InvalidArgument,
            Self::NotFound => tonic::Code::NotFound,
            Self::Conflict => tonic::Code::AlreadyExists,
            Self::PayloadTooLarge => tonic::Code::ResourceExhausted,
            Self::QuotaExceeded => tonic::Code::ResourceExhausted,
            Self::UnsupportedMediaType => tonic::Code::InvalidArgument,
            Self::StageNotAvailable => tonic::Code::Unimplemented,
            Self::Unauthenticated => tonic::Code::Unauthenticated,
            Self::PermissionDenied => tonic::Code::PermissionDenied,
            Self::Unavailable => tonic::Code::Unavailable,
            Self::DeadlineExceeded => tonic::Code::DeadlineExceeded,
            Self::Cancelled => tonic::Code::Cancelled,
            Self::Internal => tonic::Code::Internal,
        }
    }

    /// The HTTP status for this kind.
    pub fn http(self) -> StatusCode {
        match self {
            Self::InvalidArgument => StatusCode::BAD_REQUEST,
            Self::NotFound => StatusCode::NOT_FOUND,
            Self::Conflict => StatusCode::CONFLICT,
            Self::PayloadTooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            Self::QuotaExceeded => StatusCode::TOO_MANY_REQUESTS,
            Self::UnsupportedMediaType => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Self::StageNotAvailable => StatusCode::NOT_IMPLEMENTED,
            Self::Unauthenticated => StatusCode::UNAUTHORIZED,
            Self::PermissionDenied => StatusCode::FORBIDDEN,
            Self::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            Self::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
            Self::Cancelled => StatusCode::CONFLICT,
            Self::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// Classifies a gRPC status received from another service.
    pub fn from_grpc(code: tonic::Code) -> Self {
        match code {
            tonic::Code::InvalidArgument | tonic::Code::FailedPrecondition | tonic::Code::OutOfRange => {
                Self::InvalidArgument
            }
            tonic::Code::NotFound => Self::NotFound,
            tonic::Code::AlreadyExists | tonic::Code::Aborted => Self::Conflict,
            tonic::Code::ResourceExhausted => Self::PayloadTooLarge,
            tonic::Code::Unimplemented => Self::StageNotAvailable,
            tonic::Code::Unauthenticated => Self::Unauthenticated,
            tonic::Code::PermissionDenied => Self::PermissionDenied,
            tonic::Code::Unavailable => Self::Unavailable,
            tonic::Code::DeadlineExceeded => Self::DeadlineExceeded,
            tonic::Code::Cancelled => Self::Cancelled,
            _ => Self::Internal,
        }
    }

    /// Whether an operation that failed with this code may succeed if simply retried.
    pub fn is_transient(self) -> bool {
        matches!(self, Self::Unavailable | Self::DeadlineExceeded)
    }

    /// A status with this code and message.
    pub fn status(self, message: impl Into<String>) -> tonic::Status {
        tonic::Status::new(self.grpc(), message)
    }
}

impl std::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ErrorCode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        const ALL: [ErrorCode; 13] = [
            ErrorCode::InvalidArgument,
            ErrorCode::NotFound,
            ErrorCode::Conflict,
            ErrorCode::PayloadTooLarge,
            ErrorCode::QuotaExceeded,
            ErrorCode::UnsupportedMediaType,
            ErrorCode::StageNotAvailable,
            ErrorCode::Unauthenticated,
            ErrorCode::PermissionDenied,
            ErrorCode::Unavailable,
            ErrorCode::DeadlineExceeded,
            ErrorCode::Cancelled,
            ErrorCode::Internal,
        ];
        ALL.into_iter().find(|c| c.as_str() == s).ok_or_else(|| format!("unknown error code '{s}'"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_through_their_names() {
        for code in [
            ErrorCode::InvalidArgument,
            ErrorCode::QuotaExceeded,
            ErrorCode::StageNotAvailable,
            ErrorCode::Internal,
        ] {
            assert_eq!(code.as_str().parse::<ErrorCode>(), Ok(code));
        }
        assert!("nope".parse::<ErrorCode>().is_err());
    }

    #[test]
    fn only_unavailable_and_deadline_are_transient() {
        assert!(ErrorCode::from_grpc(tonic::Code::Unavailable).is_transient());
        assert!(ErrorCode::from_grpc(tonic::Code::DeadlineExceeded).is_transient());
        assert!(!ErrorCode::from_grpc(tonic::Code::InvalidArgument).is_transient());
        assert!(!ErrorCode::from_grpc(tonic::Code::Unimplemented).is_transient());
        assert_eq!(ErrorCode::from_grpc(tonic::Code::Unimplemented), ErrorCode::StageNotAvailable);
    }
}
