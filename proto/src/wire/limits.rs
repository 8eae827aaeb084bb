//! Bounds shared by the server's request validation and the clients that want to stay within them.
//! Only constants live here; the server's configurable limits take their defaults from these.

use std::time::Duration;

/// Most samples in one detection batch (the server's default `--max-batch-samples`).
pub const MAX_BATCH_SAMPLES: usize = 1000;

/// Longest vehicle id (characters of `[A-Za-z0-9._:-]`).
pub const MAX_VEHICLE_ID_LEN: usize = 128;

/// Longest resource id inside a resource name (`models/{id}` ...).
pub const MAX_RESOURCE_ID_LEN: usize = 128;

/// Largest backward time step tolerated inside a session (SPEC §3: beyond it time "goes backwards").
pub const BACKWARD_TOLERANCE_S: f64 = spoofwatch_core::evidence::MAX_BACKWARD_S;

/// Largest forward step between a session's consecutive samples (s). A sample further ahead (e.g.
/// milliseconds sent once into a seconds stream) is refused rather than accepted: accepted, it
/// would make every later sample of the vehicle "go backwards". A session that really restarts at
/// a far later time is reset first (`SessionStart.reset`, `VehicleSamples.reset`, ResetSession).
pub const MAX_FORWARD_JUMP_S: f64 = 86_400.0;

/// Latest sample time accepted at a session's start (s since the epoch, about the year 5138): a
/// later one is a time in milliseconds (1e11 ms is 1973), refused before it sets the session's
/// clock.
pub const MAX_TIMESTAMP_S: f64 = 1e11;

/// Largest gRPC message the server accepts by default (bytes).
pub const MAX_MESSAGE_BYTES: usize = 4 << 20;

/// Largest model artifact `ImportModel` accepts (bytes): 24 times the bundled model (0.7 MB, 22,000
/// parameters), room for models of about 500,000 parameters.
pub const MAX_ARTIFACT_BYTES: usize = 16 << 20;

/// Largest dataset accepted by upload or import (bytes of CSV).
pub const MAX_DATASET_BYTES: usize = 256 << 20;

/// Most records in one structured `UploadDataset` (a CSV upload is bounded by its bytes).
pub const MAX_DATASET_RECORDS: usize = 2_000_000;

/// Longest free-text display name (characters) of a dataset, model or job.
pub const MAX_DISPLAY_NAME_CHARS: usize = 256;

/// Size of the chunks `ExportModel` streams.
pub const EXPORT_CHUNK_BYTES: usize = 1 << 20;

/// Page size of the stored listings (models, datasets, operations) when a request asks for 0.
pub const DEFAULT_PAGE_SIZE: u32 = 50;

/// Larger page sizes of the stored listings are lowered to this.
pub const MAX_PAGE_SIZE: u32 = 500;

/// Page size of `ListSessions` when a request asks for 0.
pub const DEFAULT_SESSION_PAGE_SIZE: usize = 100;

/// Larger `ListSessions` page sizes are lowered to this.
pub const MAX_SESSION_PAGE_SIZE: usize = 1000;

/// Longest wait of one `WaitOperation` call.
pub const MAX_OPERATION_WAIT: Duration = Duration::from_secs(60);

/// Most epochs a training job may ask for.
pub const MAX_TRAINING_EPOCHS: u32 = spoofwatch_core::train::MAX_EPOCHS;
