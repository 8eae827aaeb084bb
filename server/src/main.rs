//! `spoofwatch-server`: parses the configuration, sets up logging, binds, and serves until SIGINT or
//! SIGTERM (`spoofwatch_server::process`).

/// mimalloc gives the memory of evicted sessions back to the operating system; glibc's allocator
/// keeps freed pages, so a server that once held 100,000 sessions would stay at that size.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[tokio::main]
async fn main() -> std::process::ExitCode {
    spoofwatch_server::process::run().await
}
