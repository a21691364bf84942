//! The `exploration.v1` API, generated from `proto/exploration/v1/exploration.proto`.
//!
//! Only types, clients and servers live here; the executive converts them into
//! its domain types at the service boundary.

#![allow(missing_docs, clippy::all, missing_debug_implementations)]

/// Types, clients and servers of package `exploration.v1`.
pub mod v1 {
    tonic::include_proto!("exploration.v1");

    /// The encoded `FileDescriptorSet`, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("exploration_v1_descriptor");
}
