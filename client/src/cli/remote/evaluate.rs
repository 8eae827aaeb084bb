//! `spoofwatch evaluate --server URL --dataset …`: an evaluation job on the server, waited for and
//! its metrics printed.

use crate::connection::{ConnectOptions, Connection};
use crate::error::reply;
use anyhow::Result;
use spoofwatch_proto::v1;

use super::jobs::{describe_result, ensure_succeeded, wait_until_done};

/// What to evaluate where.
#[derive(Debug)]
pub struct Job {
    pub server: String,
    /// Token, TLS files, compression.
    pub connect: ConnectOptions,
    /// `models/{id}` or `{id}`; empty: the active model.
    pub model: String,
    pub datasets: Vec<String>,
}

/// Creates the job, waits for it and prints its metrics (an error unless it succeeded).
pub async fn run(job: Job) -> Result<()> {
    let connection = Connection::connect_with(&job.server, &job.connect).await?;
    let request = v1::CreateEvaluationJobRequest {
        model: job.model,
        datasets: job.datasets,
    };
    let mut training = connection.training();
    let create = training.create_evaluation_job(request);
    let operation = reply("creating the evaluation job", create).await?;
    eprintln!("created evaluation job {}", operation.name);
    let operation = wait_until_done(&connection, &operation.name, None).await?;
    if let Some(result) = describe_result(&operation) {
        print!("{result}");
    }
    ensure_succeeded(&operation)
}
