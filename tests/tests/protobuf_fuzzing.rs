//! Every RPC of every Spoofwatch service (read from the compiled .proto files, so a new RPC is
//! fuzzed without a change here) gets random messages against one running server with a token
//! and the bundled model stored: random bytes, random protobuf fields (random numbers and wire
//! types), and random values of the real request type (every field of its descriptor filled with
//! empty, long, non-UTF-8-looking, NaN, infinite and extreme values). Streaming RPCs get several
//! such messages on one stream. No answer may be INTERNAL or UNKNOWN (the server's fault, or a
//! panic), no call may hang, and health stays SERVING after each RPC's round.

use crate::raw_grpc;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use prost::Message;
use prost_types::field_descriptor_proto::{Label, Type};
use prost_types::{DescriptorProto, FileDescriptorSet};
use raw_grpc::{Shape, call, code};
use spoofwatch_tests::{ServingStatus, health_of, start_server};
use tokio::task::JoinSet;
use tonic::Code;

/// Messages sent to each RPC (over several calls for streaming ones).
const MESSAGES_PER_RPC: usize = 3_000;
/// Calls in flight at once.
const CONCURRENCY: usize = 16;
/// Longest one call may take before it counts as hanging.
const CALL_BOUND: Duration = Duration::from_secs(20);
/// How long a watch with nothing to send may stay open before the test lets it go.
const QUIET_WATCH: Duration = Duration::from_millis(300);
/// RPCs whose streams legitimately stay open while there is nothing to report.
const OPEN_ENDED: [&str; 3] = [
    "/spoofwatch.v1.AlarmService/WatchAlarms",
    "/spoofwatch.v1.AlarmService/WatchIncidents",
    "/spoofwatch.v1.TrainingService/WatchJob",
];
const TOKEN: &str = "fuzz-token";

/// SplitMix64: small, seeded, reproducible.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }

    fn bytes(&mut self, len: usize) -> Vec<u8> {
        (0..len).map(|_| self.next() as u8).collect()
    }
}

/// One RPC as the descriptor set declares it.
struct Rpc {
    path: &'static str,
    shape: Shape,
    input: String,
}

/// Every RPC of the services in `spoofwatch.v1` and `google.longrunning`, and every message type.
fn rpcs_and_messages() -> (Vec<Rpc>, HashMap<String, DescriptorProto>) {
    let set = FileDescriptorSet::decode(spoofwatch_proto::FILE_DESCRIPTOR_SET)
        .expect("the embedded descriptor set decodes");
    let mut messages = HashMap::new();
    let mut rpcs = Vec::new();
    for file in &set.file {
        let package = file.package();
        for message in &file.message_type {
            collect_messages(&format!(".{package}"), message, &mut messages);
        }
        if package != "spoofwatch.v1" && package != "google.longrunning" {
            continue;
        }
        for service in &file.service {
            for method in &service.method {
                let path = format!("/{package}.{}/{}", service.name(), method.name());
                let shape = match (method.client_streaming(), method.server_streaming()) {
                    (false, false) => Shape::Unary,
                    (true, false) => Shape::ClientStreaming,
                    (false, true) => Shape::ServerStreaming,
                    (true, true) => Shape::Bidi,
                };
                rpcs.push(Rpc {
                    path: Box::leak(path.into_boxed_str()),
                    shape,
                    input: method.input_type().to_string(),
                });
            }
        }
    }
    (rpcs, messages)
}

fn collect_messages(
    scope: &str,
    message: &DescriptorProto,
    into: &mut HashMap<String, DescriptorProto>,
) {
    let name = format!("{scope}.{}", message.name());
    for nested in &message.nested_type {
        collect_messages(&name, nested, into);
    }
    into.insert(name, message.clone());
}

fn put_varint(out: &mut Vec<u8>, mut value: u64) {
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

fn put_key(out: &mut Vec<u8>, number: u32, wire_type: u8) {
    put_varint(out, (u64::from(number) << 3) | u64::from(wire_type));
}

fn put_delimited(out: &mut Vec<u8>, number: u32, payload: &[u8]) {
    put_key(out, number, 2);
    put_varint(out, payload.len() as u64);
    out.extend_from_slice(payload);
}

/// A string that may reach past the first checks (a real name or id), or one made to break them.
fn random_string(rng: &mut Rng) -> Vec<u8> {
    let pool: [&str; 12] = [
        "",
        "default",
        "models/default",
        "models/nope",
        "datasets/nope",
        "operations/nope",
        "vehicle-1",
        "veh\u{0}icle",
        "é€😀",
        "../../etc/passwd",
        " ",
        "models/",
    ];
    match rng.below(4) {
        0 | 1 => pool[rng.below(pool.len())].as_bytes().to_vec(),
        2 => {
            let len = rng.below(300);
            (0..len).map(|_| b'!' + (rng.next() % 94) as u8).collect()
        }
        _ => "ü".repeat(rng.below(5_000)).into_bytes(),
    }
}

fn random_double(rng: &mut Rng) -> f64 {
    let pool = [
        f64::NAN,
        f64::INFINITY,
        f64::NEG_INFINITY,
        0.0,
        -0.0,
        1e308,
        -1e308,
        5e-324,
        f64::MAX,
        90.0,
        -180.0,
    ];
    if rng.chance(2) {
        pool[rng.below(pool.len())]
    } else {
        (rng.next() as i64 as f64) / (1u64 << rng.below(64)) as f64
    }
}

fn random_integer(rng: &mut Rng) -> u64 {
    let pool = [
        0,
        1,
        u64::MAX,
        i64::MAX as u64,
        i64::MIN as u64,
        u64::from(u32::MAX),
        2,
        1000,
        1001,
        60,
    ];
    if rng.chance(2) {
        pool[rng.below(pool.len())]
    } else {
        rng.next() >> rng.below(64)
    }
}

/// A random value of `name`'s type, every field present or not at random (nested to a depth).
fn random_message(
    rng: &mut Rng,
    messages: &HashMap<String, DescriptorProto>,
    name: &str,
    depth: usize,
) -> Vec<u8> {
    let mut out = Vec::new();
    let Some(message) = messages.get(name) else {
        return random_fields(rng);
    };
    for field in &message.field {
        if rng.chance(3) {
            continue;
        }
        let repeats = if field.label() == Label::Repeated {
            rng.below(6)
        } else {
            1
        };
        let number = field.number() as u32;
        for _ in 0..repeats {
            match field.r#type() {
                Type::Double => {
                    put_key(&mut out, number, 1);
                    out.extend_from_slice(&random_double(rng).to_le_bytes());
                }
                Type::Float => {
                    put_key(&mut out, number, 5);
                    out.extend_from_slice(&(random_double(rng) as f32).to_le_bytes());
                }
                Type::Fixed64 | Type::Sfixed64 => {
                    put_key(&mut out, number, 1);
                    out.extend_from_slice(&random_integer(rng).to_le_bytes());
                }
                Type::Fixed32 | Type::Sfixed32 => {
                    put_key(&mut out, number, 5);
                    out.extend_from_slice(&(random_integer(rng) as u32).to_le_bytes());
                }
                Type::String | Type::Bytes => {
                    let value = if field.r#type() == Type::Bytes && rng.chance(2) {
                        let len = rng.below(2_000);
                        rng.bytes(len)
                    } else {
                        random_string(rng)
                    };
                    put_delimited(&mut out, number, &value);
                }
                Type::Message | Type::Group => {
                    let nested = if depth < 4 {
                        random_message(rng, messages, field.type_name(), depth + 1)
                    } else {
                        Vec::new()
                    };
                    put_delimited(&mut out, number, &nested);
                }
                // Varints: every integer kind, bools and enums (known and unknown values).
                _ => {
                    put_key(&mut out, number, 0);
                    put_varint(&mut out, random_integer(rng));
                }
            }
        }
    }
    out
}

/// Random fields: random numbers and wire types, payloads that may or may not fit them.
fn random_fields(rng: &mut Rng) -> Vec<u8> {
    let mut out = Vec::new();
    for _ in 0..rng.below(8) {
        let number = if rng.chance(4) {
            (rng.next() % (1 << 29)) as u32
        } else {
            1 + rng.below(20) as u32
        };
        let wire_type = (rng.next() % 8) as u8;
        put_key(&mut out, number, wire_type);
        match wire_type {
            0 => put_varint(&mut out, rng.next()),
            1 => out.extend_from_slice(&rng.bytes(8)),
            2 => {
                let len = rng.below(40);
                // Sometimes a length that runs past the end.
                put_varint(&mut out, (len + rng.below(2) * rng.below(100)) as u64);
                out.extend_from_slice(&rng.bytes(len));
            }
            5 => out.extend_from_slice(&rng.bytes(4)),
            _ => {}
        }
    }
    out
}

/// One message for `rpc`: a third random bytes, a third random fields, a third its own type.
fn random_request(
    rng: &mut Rng,
    messages: &HashMap<String, DescriptorProto>,
    rpc: &Rpc,
) -> Vec<u8> {
    match rng.below(3) {
        0 => {
            let len = rng.below(64);
            rng.bytes(len)
        }
        1 => random_fields(rng),
        _ => random_message(rng, messages, &rpc.input, 0),
    }
}

/// Sends `MESSAGES_PER_RPC` random messages to `rpc`; panics on a forbidden code or a hang.
async fn fuzz(
    channel: &tonic::transport::Channel,
    rng: &mut Rng,
    messages: &HashMap<String, DescriptorProto>,
    rpc: &Rpc,
) -> HashMap<Code, usize> {
    let streaming_in = matches!(rpc.shape, Shape::ClientStreaming | Shape::Bidi);
    let open_ended = OPEN_ENDED.contains(&rpc.path);
    let mut calls = JoinSet::new();
    let mut codes: HashMap<Code, usize> = HashMap::new();
    let mut sent = 0;
    while sent < MESSAGES_PER_RPC || !calls.is_empty() {
        if sent < MESSAGES_PER_RPC && calls.len() < CONCURRENCY {
            let count = if streaming_in { 1 + rng.below(8) } else { 1 };
            let batch: Vec<Vec<u8>> = (0..count)
                .map(|i| {
                    // The first message of a stream is mostly of its type, to get past headers.
                    if i == 0 && streaming_in && !rng.chance(4) {
                        random_message(rng, messages, &rpc.input, 0)
                    } else {
                        random_request(rng, messages, rpc)
                    }
                })
                .collect();
            sent += count;
            let (channel, path, shape) = (channel.clone(), rpc.path, rpc.shape);
            calls.spawn(async move {
                let bound = if open_ended { QUIET_WATCH } else { CALL_BOUND };
                let started = Instant::now();
                let outcome =
                    call(&channel, Some(TOKEN), path, shape, batch.clone(), 2, bound).await;
                (outcome, batch, started.elapsed())
            });
            continue;
        }
        let Some(joined) = calls.join_next().await else {
            continue;
        };
        let (outcome, batch, elapsed) = joined.expect("the call task ends");
        let Some(outcome) = outcome else {
            assert!(
                open_ended,
                "{} did not answer within {elapsed:?}; messages sent: {batch:02x?}",
                rpc.path
            );
            *codes.entry(Code::Ok).or_default() += 1;
            continue;
        };
        let code = code(&outcome);
        assert!(
            !matches!(code, Code::Internal | Code::Unknown),
            "{} answered {outcome:?} to {batch:02x?}",
            rpc.path
        );
        *codes.entry(code).or_default() += 1;
    }
    codes
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn random_messages_to_every_rpc_get_no_internal_error_and_no_hang() {
    let (_dir, server, clients) = start_server(|config| {
        config.auth_token = Some(TOKEN.to_string());
    })
    .await;
    let channel = server.channel().await;
    let (rpcs, messages) = rpcs_and_messages();
    assert_eq!(rpcs.len(), 35, "every RPC of the six services");
    let started = Instant::now();
    let mut rng = Rng(0x5eed_f00d);
    for rpc in &rpcs {
        let round = Instant::now();
        let codes = fuzz(&channel, &mut rng, &messages, rpc).await;
        eprintln!("{} in {:?}: {codes:?}", rpc.path, round.elapsed());
        assert_eq!(
            health_of(&server, "").await,
            ServingStatus::Serving,
            "after {}",
            rpc.path
        );
    }
    eprintln!("{} RPCs fuzzed in {:?}", rpcs.len(), started.elapsed());
    drop(clients);
    server.stop().await;
}
