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

/// Largest message a client or the executive decodes: a map update with big
/// patches, a whole 25-million-cell map with its frontier.
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024 * 1024;

/// Per-cell labels as run-length pairs: (label, run length), each a
/// little-endian `u32`, row-major. The wire form of
/// `SetGivenSegmentationRequest.label_runs`, and how the store keeps labels.
pub mod label_runs {
    /// Bytes a (label, run length) pair takes.
    pub const PAIR_BYTES: usize = 8;

    /// The runs of `labels`.
    pub fn encode(labels: &[u32]) -> Vec<u8> {
        let mut out = Vec::with_capacity(runs(labels).count() * PAIR_BYTES);
        for (label, run) in runs(labels) {
            out.extend_from_slice(&label.to_le_bytes());
            out.extend_from_slice(&run.to_le_bytes());
        }
        out
    }

    /// Bytes `encode(labels)` takes, without making them.
    pub fn encoded_len(labels: &[u32]) -> usize {
        runs(labels).count() * PAIR_BYTES
    }

    /// `(label, run length)` for each run, runs of at most `u32::MAX`.
    fn runs(labels: &[u32]) -> impl Iterator<Item = (u32, u32)> + '_ {
        let mut rest = labels;
        std::iter::from_fn(move || {
            let &label = rest.first()?;
            let run = rest.iter().take_while(|&&l| l == label).count().min(u32::MAX as usize);
            rest = &rest[run..];
            Some((label, run as u32))
        })
    }

    /// The labels of `len` cells. Runs that are not whole pairs, or that
    /// add up to anything but `len`, are refused before anything is
    /// allocated for them; the error says what they hold.
    pub fn decode(bytes: &[u8], len: usize) -> Result<Vec<u32>, String> {
        if !bytes.len().is_multiple_of(8) {
            return Err(format!("hold {} bytes, not (label, run length) pairs of 8", bytes.len()));
        }
        let pairs = || {
            bytes.chunks_exact(8).map(|p| {
                (u32::from_le_bytes([p[0], p[1], p[2], p[3]]), u32::from_le_bytes([p[4], p[5], p[6], p[7]]) as usize)
            })
        };
        let total: u64 = pairs().map(|(_, run)| run as u64).sum();
        if total != len as u64 {
            return Err(format!("cover {total} cells, not the map's {len}"));
        }
        let mut labels = Vec::with_capacity(len);
        for (label, run) in pairs() {
            labels.extend(std::iter::repeat_n(label, run));
        }
        Ok(labels)
    }
}

impl v1::Segmentation {
    /// The label of each of the `cells` of the mission's map, from whichever
    /// form the executive sent (`label_runs`, or `labels` from an executive
    /// that predates them); `None` when it sent neither.
    pub fn labels_per_cell(&self, cells: usize) -> Result<Option<Vec<u32>>, String> {
        if !self.label_runs.is_empty() {
            return label_runs::decode(&self.label_runs, cells).map(Some).map_err(|e| format!("label_runs {e}"));
        }
        if self.labels.is_empty() {
            return Ok(None);
        }
        if self.labels.len() != cells * 4 {
            return Err(format!("labels hold {} bytes, not 4 for each of the map's {cells} cells", self.labels.len()));
        }
        Ok(Some(self.labels.chunks_exact(4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()))
    }
}

/// Prost's codec, except that a message that is not valid protobuf is
/// INVALID_ARGUMENT (the sender's error), not INTERNAL.
pub mod codec {
    use tonic::Status;
    use tonic::codec::{BufferSettings, DecodeBuf, Decoder};
    use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

    /// See the module.
    #[derive(Debug, Clone, Default)]
    pub struct Codec<T, U>(ProstCodec<T, U>);

    impl<T, U> tonic::codec::Codec for Codec<T, U>
    where
        T: prost::Message + Send + 'static,
        U: prost::Message + Default + Send + 'static,
    {
        type Encode = T;
        type Decode = U;
        type Encoder = ProstEncoder<T>;
        type Decoder = StrictDecoder<U>;

        fn encoder(&mut self) -> Self::Encoder {
            self.0.encoder()
        }

        fn decoder(&mut self) -> Self::Decoder {
            StrictDecoder(self.0.decoder())
        }
    }

    /// See the module.
    #[derive(Debug, Clone)]
    pub struct StrictDecoder<U>(ProstDecoder<U>);

    impl<U: prost::Message + Default> Decoder for StrictDecoder<U> {
        type Item = U;
        type Error = Status;

        fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
            self.0.decode(buf).map_err(|status| {
                Status::invalid_argument(format!(
                    "the message is not a valid protobuf encoding of the call's request: {}",
                    status.message()
                ))
            })
        }

        fn buffer_settings(&self) -> BufferSettings {
            self.0.buffer_settings()
        }
    }
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

pub mod client;
pub mod files;
pub mod replicas;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn label_runs_come_back_as_the_labels_they_were_made_from() {
        let labels = [0, 0, 7, 7, 7, 0, 3, 3, 9];
        let runs = label_runs::encode(&labels);
        assert_eq!(runs.len(), 5 * label_runs::PAIR_BYTES);
        assert_eq!(label_runs::encoded_len(&labels), runs.len());
        assert_eq!(label_runs::decode(&runs, labels.len()).unwrap(), labels);
        assert!(label_runs::decode(&runs, labels.len() + 1).unwrap_err().contains("cover 9 cells"));
        assert_eq!(label_runs::encoded_len(&[]), 0);
    }

    #[test]
    fn a_segmentation_gives_the_same_labels_in_either_form() {
        let labels = vec![0, 1, 1, 2, 2, 2];
        let per_cell = v1::Segmentation {
            labels: labels.iter().flat_map(|l: &u32| l.to_le_bytes()).collect(),
            ..Default::default()
        };
        let as_runs = v1::Segmentation { label_runs: label_runs::encode(&labels), ..Default::default() };
        assert_eq!(per_cell.labels_per_cell(6).unwrap(), Some(labels.clone()));
        assert_eq!(as_runs.labels_per_cell(6).unwrap(), Some(labels));
        assert_eq!(v1::Segmentation::default().labels_per_cell(6).unwrap(), None);
        assert!(per_cell.labels_per_cell(7).unwrap_err().contains("24 bytes"));
        assert!(as_runs.labels_per_cell(5).unwrap_err().starts_with("label_runs cover 6"));
    }
}
