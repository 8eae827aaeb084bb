//! Calls with raw message bytes, for tests that send what no generated client would: a codec that
//! passes bytes through, and one call per RPC shape, each bounded in time. Shared by test files
//! through `crate::raw_grpc`.

#![allow(dead_code)]

use std::time::Duration;

use prost::bytes::{Buf, BufMut};
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

/// A codec whose messages are their encoded bytes.
#[derive(Clone, Copy, Debug, Default)]
pub struct RawCodec;

impl Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> RawCodec {
        RawCodec
    }

    fn decoder(&mut self) -> RawCodec {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put_slice(&item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, Status> {
        Ok(Some(src.copy_to_bytes(src.remaining()).to_vec()))
    }
}

/// How an RPC streams: whether the client sends a stream, and whether the server replies with one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    Unary,
    ClientStreaming,
    ServerStreaming,
    Bidi,
}

/// What a raw call ended with: OK (with the replies read) or a status.
pub type Outcome = Result<usize, Status>;

/// Calls `path` (`/package.Service/Method`) with `messages` (one for unary and server-streaming
/// calls) and, for streaming replies, reads until the end or `replies` replies, whichever comes
/// first. `None` when the call does not end within `bound`. `token`: a bearer token to send.
pub async fn call(
    channel: &Channel,
    token: Option<&str>,
    path: &'static str,
    shape: Shape,
    messages: Vec<Vec<u8>>,
    replies: usize,
    bound: Duration,
) -> Option<Outcome> {
    tokio::time::timeout(
        bound,
        call_unbounded(channel, token, path, shape, messages, replies),
    )
    .await
    .ok()
}

async fn call_unbounded(
    channel: &Channel,
    token: Option<&str>,
    path: &'static str,
    shape: Shape,
    mut messages: Vec<Vec<u8>>,
    replies: usize,
) -> Outcome {
    let mut grpc = tonic::client::Grpc::new(channel.clone());
    grpc.ready()
        .await
        .map_err(|e| Status::unavailable(e.to_string()))?;
    let path = PathAndQuery::from_static(path);
    match shape {
        Shape::Unary => {
            let message = messages.pop().unwrap_or_default();
            grpc.unary(with_token(message, token), path, RawCodec)
                .await
                .map(|_| 1)
        }
        Shape::ServerStreaming => {
            let message = messages.pop().unwrap_or_default();
            let mut stream = grpc
                .server_streaming(with_token(message, token), path, RawCodec)
                .await?
                .into_inner();
            read_replies(&mut stream, replies).await
        }
        Shape::ClientStreaming => grpc
            .client_streaming(
                with_token(tokio_stream::iter(messages), token),
                path,
                RawCodec,
            )
            .await
            .map(|_| 1),
        Shape::Bidi => {
            let mut replies_stream = grpc
                .streaming(
                    with_token(tokio_stream::iter(messages), token),
                    path,
                    RawCodec,
                )
                .await?
                .into_inner();
            read_replies(&mut replies_stream, replies).await
        }
    }
}

/// `message` as a request carrying `token` as a bearer token, when given.
fn with_token<M>(message: M, token: Option<&str>) -> Request<M> {
    let mut request = Request::new(message);
    if let Some(token) = token {
        let value = format!("Bearer {token}").parse().expect("an ASCII token");
        request.metadata_mut().insert("authorization", value);
    }
    request
}

async fn read_replies(stream: &mut tonic::Streaming<Vec<u8>>, most: usize) -> Outcome {
    let mut read = 0;
    while read < most {
        match stream.message().await? {
            Some(_) => read += 1,
            None => break,
        }
    }
    Ok(read)
}

/// The code of an outcome (OK for a call that succeeded).
pub fn code(outcome: &Outcome) -> Code {
    match outcome {
        Ok(_) => Code::Ok,
        Err(status) => status.code(),
    }
}
