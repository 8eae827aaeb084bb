//! Generated gRPC types and services of the Spoofwatch API, plus [`wire`]: the one hand-written layer
//! between them and the core's types (conversions, resource names, limits), and [`codec`]: the
//! servers' codec (a malformed request is INVALID_ARGUMENT), and [`pem`]: the TLS files both ends
//! read, checked as they are read. The generated modules
//! mirror the proto packages because generated code refers across them with relative paths.

pub mod codec;
pub mod pem;
pub mod wire;

#[allow(clippy::all, missing_docs, rust_2018_idioms)]
pub mod spoofwatch {
    /// `spoofwatch.v1`: detection, models, datasets, training, alarms.
    pub mod v1 {
        tonic::include_proto!("spoofwatch.v1");
        include!(concat!(env!("OUT_DIR"), "/servers/spoofwatch.v1.rs"));
    }
}

#[allow(clippy::all, missing_docs, rust_2018_idioms)]
pub mod google {
    /// `google.longrunning`: the Operations service used for jobs.
    pub mod longrunning {
        tonic::include_proto!("google.longrunning");
        include!(concat!(env!("OUT_DIR"), "/servers/google.longrunning.rs"));
    }
}

pub use google::longrunning;
pub use spoofwatch::v1;

/// Encoded `FileDescriptorSet` of every file above, for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("spoofwatch_descriptor");
