//! The CLI and the client library as a user runs them (the real `spoofwatch` binary, in-process
//! servers), one module per behaviour, linked into one test binary: each binary links the whole
//! server and client, so one link instead of one per file is most of their build time.

mod cli_connections;
mod offline_cli;
mod remote_cli;
mod replay_end_to_end;
