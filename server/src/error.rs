//! The executive's errors, and the one place they become gRPC statuses.

use exploration::fusion::PatchError;
use exploration::policy::PolicyError;
use exploration_proto::client::RETRY_PUSHBACK_METADATA;

use crate::store::{FailureKind, StoreError};

/// Everything that can go wrong in a request. The message of every variant
/// but [`Error::Store`] and [`Error::Internal`] is written for the client: it
/// says what was wrong and what to send instead.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The request is malformed, whatever the executive's state.
    #[error("{0}")]
    InvalidArgument(String),
    /// A mission, robot or task that does not exist.
    #[error("{0}")]
    NotFound(String),
    /// The request repeats one already carried out.
    #[error("{0}")]
    AlreadyExists(String),
    /// The request does not fit the executive's state.
    #[error("{0}")]
    FailedPrecondition(String),
    /// A quota would be exceeded.
    #[error("{0}")]
    ResourceExhausted(String),
    /// No valid token came with the request.
    #[error("{0}")]
    Unauthenticated(String),
    /// The token does not allow this.
    #[error("{0}")]
    PermissionDenied(String),
    /// Too much work is waiting: refused at once, to be retried after a pause.
    #[error("{0}")]
    Overloaded(String),
    /// Another replica acts for the mission (replicas sharing a database):
    /// the client retries there, or, without an address, anywhere shortly.
    #[error("{message}")]
    Elsewhere {
        /// What happened, for the client.
        message: String,
        /// Where the replica that holds the mission is reached, if known.
        owner: Option<String>,
    },
    /// The executive is shutting down.
    #[error("the executive is shutting down; retry against its successor")]
    ShuttingDown,
    /// Persistence failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A bug or an unexpected failure.
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<PatchError> for Error {
    fn from(e: PatchError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<crate::validate::Invalid> for Error {
    fn from(e: crate::validate::Invalid) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<PolicyError> for Error {
    fn from(e: PolicyError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<Error> for tonic::Status {
    fn from(e: Error) -> Self {
        use tonic::Status;
        match e {
            Error::InvalidArgument(m) => Status::invalid_argument(m),
            Error::NotFound(m) => Status::not_found(m),
            Error::AlreadyExists(m) => Status::already_exists(m),
            Error::FailedPrecondition(m) => Status::failed_precondition(m),
            Error::ResourceExhausted(m) => Status::resource_exhausted(m),
            Error::Unauthenticated(m) => Status::unauthenticated(m),
            Error::PermissionDenied(m) => Status::permission_denied(m),
            Error::ShuttingDown => Status::unavailable(e.to_string()),
            Error::Overloaded(m) => overloaded(m),
            Error::Elsewhere { message, owner } => elsewhere(message, owner.as_deref()),
            Error::Store(StoreError::Unsupported(m)) => Status::failed_precondition(m),
            // Internals are logged here, once, and never shown to the client.
            Error::Store(cause) => {
                tracing::error!(error = %cause, "store failure");
                match cause.kind() {
                    FailureKind::Fenced => elsewhere(
                        "another replica has taken this mission over: nothing of this request was written; retry"
                            .to_owned(),
                        None,
                    ),
                    FailureKind::Full => Status::resource_exhausted(
                        "the executive's disk is full: nothing of this request was written; reads still work, \
                         and writes will once space is freed (retry later)",
                    ),
                    FailureKind::Transient => Status::unavailable(
                        "the executive could not write to its database just now: nothing of this request was \
                         written; retry",
                    ),
                    FailureKind::Internal => Status::internal(
                        "internal error: the executive could not persist or read state; it logged the cause",
                    ),
                }
            }
            Error::Internal(cause) => {
                tracing::error!(error = %cause, "internal failure");
                Status::internal("internal error; the executive logged the cause")
            }
        }
    }
}

/// How long a client should wait before retrying a call refused to shed
/// load, in the header gRPC's own retry machinery reads.
pub const RETRY_PUSHBACK_MS: u64 = 100;

/// UNAVAILABLE with the owner's address (in
/// [`exploration_proto::replicas::OWNER_METADATA`], which the project's
/// clients follow) and a retry hint.
pub fn elsewhere(message: String, owner: Option<&str>) -> tonic::Status {
    let mut status = tonic::Status::unavailable(message);
    let metadata = status.metadata_mut();
    metadata.insert(RETRY_PUSHBACK_METADATA, RETRY_PUSHBACK_MS.into());
    if let Some(owner) = owner.and_then(|o| o.parse().ok()) {
        metadata.insert(exploration_proto::replicas::OWNER_METADATA, owner);
    }
    status
}

/// RESOURCE_EXHAUSTED with a retry hint (`grpc-retry-pushback-ms`).
pub fn overloaded(message: String) -> tonic::Status {
    overloaded_for(message, std::time::Duration::from_millis(RETRY_PUSHBACK_MS))
}

/// RESOURCE_EXHAUSTED asking the caller to wait `wait` (whole
/// milliseconds, at least one) before it calls again.
pub fn overloaded_for(message: String, wait: std::time::Duration) -> tonic::Status {
    let ms = u64::try_from(wait.as_millis()).unwrap_or(u64::MAX).max(1);
    let mut status = tonic::Status::resource_exhausted(message);
    status.metadata_mut().insert(RETRY_PUSHBACK_METADATA, ms.into());
    status
}

/// An error and its causes on one line, for a person: each cause that its
/// error's message does not already state is added after a colon. (Our
/// errors name their cause in their own message, and so do sqlx's and
/// std's, so the usual chain would say the same thing three times.)
pub fn report(error: &(dyn std::error::Error + 'static)) -> String {
    let mut line = String::new();
    let mut cause = Some(error);
    while let Some(error) = cause {
        // A status says its code and message, and its own root cause, on
        // one line; its Display is a debugging dump.
        let (said, rest) = match error.downcast_ref::<tonic::Status>() {
            Some(status) => (exploration_proto::client::status_line(status), None),
            None => (error.to_string(), error.source()),
        };
        if !line.contains(&said) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&said);
        }
        cause = rest;
    }
    line
}

#[cfg(test)]
mod tests {
    use super::report;

    #[derive(Debug, thiserror::Error)]
    #[error("could not open the store x.db: {0}")]
    struct Outer(#[source] Inner);

    #[derive(Debug, thiserror::Error)]
    #[error("database error: {0}")]
    struct Inner(#[source] std::io::Error);

    #[derive(Debug, thiserror::Error)]
    #[error("lock file held")]
    struct Terse(#[source] std::io::Error);

    #[test]
    fn a_cause_already_stated_is_not_repeated_and_one_not_stated_is_added() {
        let repeated = Outer(Inner(std::io::Error::other("file is not a database")));
        assert_eq!(report(&repeated), "could not open the store x.db: database error: file is not a database");
        let terse = Terse(std::io::Error::other("Resource busy"));
        assert_eq!(report(&terse), "lock file held: Resource busy");
    }

    #[derive(Debug, thiserror::Error)]
    #[error("CreateMission")]
    struct Call(#[source] tonic::Status);

    #[test]
    fn a_status_in_the_chain_is_its_code_and_message_not_its_debugging_dump() {
        let refused = Call(tonic::Status::invalid_argument("unknown policy \"nosuch\""));
        assert_eq!(report(&refused), "CreateMission: InvalidArgument: unknown policy \"nosuch\"");
    }
}
