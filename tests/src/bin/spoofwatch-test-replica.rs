//! The Spoofwatch server as a process of its own, built with the black-box tests so that they can
//! kill one (`kill -9`): the very process of the `spoofwatch-server` binary
//! (`spoofwatch_server::process`), flags and log lines included.

#[tokio::main]
async fn main() -> std::process::ExitCode {
    spoofwatch_server::process::run().await
}
