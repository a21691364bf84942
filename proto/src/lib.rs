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

/// Client-side bearer authentication: adds `authorization: Bearer <token>`
/// to every request, or nothing without a token. Use with
/// `XClient::with_interceptor(channel, Bearer::new(token)?)`.
#[derive(Debug, Clone, Default)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl Bearer {
    /// A bearer for `token`; none when `None` or blank.
    pub fn new(token: Option<&str>) -> Result<Self, tonic::metadata::errors::InvalidMetadataValue> {
        match token.map(str::trim).filter(|t| !t.is_empty()) {
            Some(t) => Ok(Self(Some(format!("Bearer {t}").parse()?))),
            None => Ok(Self(None)),
        }
    }
}

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}
