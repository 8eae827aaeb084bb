//! The codec of every generated service server: tonic-prost's, except that a request that is not a
//! valid protobuf message of its type is INVALID_ARGUMENT (the client sent it), with prost's reason,
//! instead of tonic-prost's INTERNAL. Clients keep tonic-prost's codec: a malformed reply is not
//! their caller's fault. Owns nothing else of the wire.

use std::marker::PhantomData;

use prost::Message;
use tonic::Status;
use tonic::codec::{Codec, DecodeBuf, Decoder};
use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

/// Longest part of prost's reason shown to the client (it names nested fields, so it may grow with
/// the nesting of a hostile message).
const MAX_REASON_CHARS: usize = 200;

/// [`ProstCodec`] with decode errors mapped to INVALID_ARGUMENT.
#[derive(Debug, Clone)]
pub struct RequestCodec<T, U> {
    inner: ProstCodec<T, U>,
}

impl<T, U> Default for RequestCodec<T, U> {
    fn default() -> Self {
        Self {
            inner: ProstCodec::default(),
        }
    }
}

impl<T, U> Codec for RequestCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = RequestDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        self.inner.encoder()
    }

    fn decoder(&mut self) -> Self::Decoder {
        RequestDecoder {
            inner: self.inner.decoder(),
            _message: PhantomData,
        }
    }
}

/// Decodes requests of type `U`; see [`RequestCodec`].
#[derive(Debug, Clone)]
pub struct RequestDecoder<U> {
    inner: ProstDecoder<U>,
    _message: PhantomData<U>,
}

impl<U: Message + Default> Decoder for RequestDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        // tonic-prost's decoder answers every decode error INTERNAL with prost's text; nothing
        // else fails there.
        self.inner
            .decode(buf)
            .map_err(|status| invalid_request::<U>(status.message()))
    }

    fn buffer_settings(&self) -> tonic::codec::BufferSettings {
        self.inner.buffer_settings()
    }
}

/// INVALID_ARGUMENT naming the request type and prost's reason (bounded).
fn invalid_request<U>(reason: &str) -> Status {
    let reason = reason.trim_start_matches("failed to decode Protobuf message: ");
    let shown: String = reason.chars().take(MAX_REASON_CHARS).collect();
    let cut = if shown.len() < reason.len() {
        "…"
    } else {
        ""
    };
    Status::invalid_argument(format!(
        "request is not a valid {} protobuf message: {shown}{cut}",
        proto_name::<U>()
    ))
}

/// The protobuf name of a generated message (`spoofwatch.v1.DetectRequest`), from its Rust path.
fn proto_name<U>() -> String {
    let path = std::any::type_name::<U>();
    let path = path.strip_prefix("spoofwatch_proto::").unwrap_or(path);
    path.replace("::", ".")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_decode_error_names_the_request_type_and_is_bounded() {
        let long = format!("failed to decode Protobuf message: {}", "x".repeat(10_000));
        let status = invalid_request::<crate::v1::DetectRequest>(&long);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(
            status.message().starts_with(
                "request is not a valid spoofwatch.v1.DetectRequest protobuf message: xxx"
            ),
            "{}",
            status.message()
        );
        assert!(status.message().chars().count() < 300);
        let operations = proto_name::<crate::longrunning::GetOperationRequest>();
        assert_eq!(operations, "google.longrunning.GetOperationRequest");
    }
}
