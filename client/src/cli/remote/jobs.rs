//! `spoofwatch jobs`: training and evaluation jobs (google.longrunning operations).
//!
//! It owns how operations are decoded, described and waited for; listing and tables come from
//! `remote`, models are described by `models`.

use std::time::{Duration, Instant};

use crate::connection::Connection;
use crate::error::describe_rpc_status;
use crate::retry::{self, Idempotency};
use anyhow::{Result, bail};
use prost::Message;
use spoofwatch_proto::longrunning;
use spoofwatch_proto::longrunning::operation::Result as OperationResult;
use spoofwatch_proto::v1;

use super::{ResourceArgs, all_pages, opt, print_table, time};
use crate::report::metrics_table;

/// The server's longest single WaitOperation.
const MAX_WAIT_PER_CALL: Duration = Duration::from_secs(60);

/// `spoofwatch {resource} <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// List jobs.
    List {
        /// `kind=training`, `kind=evaluation`, `done=true`, `done=false`, joined with ` AND `.
        #[arg(long, default_value = "")]
        filter: String,
    },
    /// Show a job's state, progress and result.
    Get {
        /// `operations/{id}` or `{id}`.
        name: String,
    },
    /// Ask a job to stop.
    Cancel {
        /// `operations/{id}` or `{id}`.
        name: String,
    },
    /// Wait until a job is done and show its result (fails unless it succeeded).
    Wait {
        /// `operations/{id}` or `{id}`.
        name: String,
        /// Give up after this many seconds (default: wait as long as it takes).
        #[arg(long, value_parser = parse_timeout)]
        timeout: Option<f64>,
    },
}

/// Seconds: finite and > 0.
pub fn parse_timeout(text: &str) -> Result<f64, String> {
    let seconds: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number of seconds"))?;
    if !(seconds.is_finite() && seconds > 0.0) {
        return Err(format!("must be a positive number of seconds, got {text}"));
    }
    Ok(seconds)
}

/// An operation's progress (its `JobMetadata`), if it carries one.
pub fn job_metadata(operation: &longrunning::Operation) -> Option<v1::JobMetadata> {
    let any = operation.metadata.as_ref()?;
    v1::JobMetadata::decode(any.value.as_slice()).ok()
}

/// A job state as a short word.
pub fn state_name(state: i32) -> &'static str {
    match v1::JobState::try_from(state) {
        Ok(v1::JobState::Queued) => "queued",
        Ok(v1::JobState::Running) => "running",
        Ok(v1::JobState::Succeeded) => "succeeded",
        Ok(v1::JobState::Failed) => "failed",
        Ok(v1::JobState::Cancelled) => "cancelled",
        _ => "unknown",
    }
}

/// One line of progress: `epoch 3/30  loss 0.1234  val 0.2345  AUROC 0.9876  ETA 42 s`.
pub fn progress_line(m: &v1::JobMetadata) -> String {
    let mut line = format!("{} epoch {}/{}", state_name(m.state), m.epoch, m.max_epochs);
    if m.epoch > 0 {
        line.push_str(&format!(
            "  loss {:.4}  val {:.4}  AUROC {}",
            m.train_loss,
            m.val_loss,
            opt(m.val_auroc, 4)
        ));
    }
    if let Some(eta) = m.eta_s {
        line.push_str(&format!("  ETA {eta:.0} s"));
    }
    line
}

/// The finished operation's result (or error), several lines; `None` while it runs.
pub fn describe_result(operation: &longrunning::Operation) -> Option<String> {
    match operation.result.as_ref()? {
        OperationResult::Error(status) => Some(format!("error: {}\n", describe_rpc_status(status))),
        OperationResult::Response(any) => Some(match any.type_url.rsplit('/').next() {
            Some("spoofwatch.v1.TrainingJobResult") => {
                match v1::TrainingJobResult::decode(any.value.as_slice()) {
                    Ok(result) => describe_training_result(&result),
                    Err(error) => format!("undecodable training result: {error}\n"),
                }
            }
            Some("spoofwatch.v1.EvaluationJobResult") => {
                match v1::EvaluationJobResult::decode(any.value.as_slice()) {
                    Ok(result) => describe_evaluation_result(&result),
                    Err(error) => format!("undecodable evaluation result: {error}\n"),
                }
            }
            _ => format!("result of type {}\n", any.type_url),
        }),
    }
}

/// The registered model and its metrics.
pub fn describe_training_result(result: &v1::TrainingJobResult) -> String {
    let mut out = match &result.model {
        Some(model) => format!(
            "registered model:\n{}",
            super::models::describe_without_metrics(model)
        ),
        None => "the trained model is no longer registered\n".to_string(),
    };
    let mut rows = Vec::new();
    if let Some(validation) = &result.validation {
        rows.push(("validation", validation));
    }
    if let Some(test) = &result.test {
        rows.push(("test (chronological 15%)", test));
    }
    if !rows.is_empty() {
        out.push_str(&metrics_table(&rows));
    }
    if let Some(report) = &result.fleet_fit {
        out.push_str(&crate::cli::fit_report::render(report));
    }
    out
}

fn describe_evaluation_result(result: &v1::EvaluationJobResult) -> String {
    let mut per_vehicle: Vec<(&String, &v1::Metrics)> = result.per_vehicle.iter().collect();
    per_vehicle.sort_by(|a, b| a.0.cmp(b.0));
    let mut rows: Vec<(&str, &v1::Metrics)> = Vec::new();
    if let Some(overall) = &result.overall {
        rows.push(("overall", overall));
    }
    rows.extend(per_vehicle.iter().map(|(v, m)| (v.as_str(), *m)));
    format!("evaluated {}\n{}", result.model, metrics_table(&rows))
}

/// An operation: name, kind, state, times, progress and (when done) result.
pub fn describe_operation(operation: &longrunning::Operation) -> String {
    let mut out = format!("{}\n", operation.name);
    if let Some(m) = job_metadata(operation) {
        out.push_str(&format!(
            "  kind      {}\n  state     {}\n  created   {}\n  started   {}\n  ended     {}\n  progress  {}\n",
            m.kind,
            state_name(m.state),
            time(m.create_time.as_ref()),
            time(m.start_time.as_ref()),
            time(m.end_time.as_ref()),
            progress_line(&m),
        ));
        if !m.message.is_empty() {
            out.push_str(&format!("  message   {}\n", m.message));
        }
    }
    if let Some(result) = describe_result(operation) {
        out.push_str(&result);
    }
    out
}

/// Fails unless the finished operation succeeded.
pub fn ensure_succeeded(operation: &longrunning::Operation) -> Result<()> {
    match &operation.result {
        Some(OperationResult::Response(_)) => Ok(()),
        Some(OperationResult::Error(status)) => bail!(
            "{} did not succeed: {}",
            operation.name,
            describe_rpc_status(status)
        ),
        None if operation.done => bail!("{} finished without a result", operation.name),
        None => bail!("{} is still running", operation.name),
    }
}

/// Waits (in calls of at most 60 s) until the operation is done or `timeout` has passed; returns
/// its latest state.
pub async fn wait_until_done(
    connection: &Connection,
    name: &str,
    timeout: Option<Duration>,
) -> Result<longrunning::Operation> {
    let started = Instant::now();
    let mut client = connection.operations();
    loop {
        let remaining = timeout.map(|t| t.saturating_sub(started.elapsed()));
        let this_call = remaining.map_or(MAX_WAIT_PER_CALL, |r| r.min(MAX_WAIT_PER_CALL));
        let request = longrunning::WaitOperationRequest {
            name: name.to_string(),
            timeout: Some(prost_types::Duration {
                seconds: this_call.as_secs() as i64,
                nanos: this_call.subsec_nanos() as i32,
            }),
        };
        let operation = retry::unary(
            format!("waiting for {name}"),
            Idempotency::Idempotent,
            async || client.wait_operation(request.clone()).await,
        )
        .await?;
        if operation.done || remaining.is_some_and(|r| r <= this_call) {
            return Ok(operation);
        }
    }
}

pub async fn run(args: Args) -> Result<()> {
    let connection = args.server.connect().await?;
    let mut client = connection.operations();
    match args.command {
        Command::List { filter } => {
            let operations = all_pages(
                "listing jobs",
                async |page_token| {
                    let request = longrunning::ListOperationsRequest {
                        name: String::new(),
                        filter: filter.clone(),
                        page_size: 0,
                        page_token,
                    };
                    client.list_operations(request).await
                },
                |page| (page.operations, page.next_page_token),
            )
            .await?;
            let header = ["name", "kind", "state", "epoch", "created", "message"];
            print_table(&header, &operations, |op| {
                let m = job_metadata(op).unwrap_or_default();
                vec![
                    op.name.clone(),
                    m.kind.clone(),
                    state_name(m.state).to_string(),
                    format!("{}/{}", m.epoch, m.max_epochs),
                    time(m.create_time.as_ref()),
                    m.message.clone(),
                ]
            });
        }
        Command::Get { name } => {
            let request = longrunning::GetOperationRequest { name: name.clone() };
            let operation = retry::unary(
                format!("getting {name}"),
                Idempotency::Idempotent,
                async || client.get_operation(request.clone()).await,
            )
            .await?;
            print!("{}", describe_operation(&operation));
        }
        Command::Cancel { name } => {
            let request = longrunning::CancelOperationRequest { name: name.clone() };
            retry::unary(
                format!("cancelling {name}"),
                Idempotency::Idempotent,
                async || client.cancel_operation(request.clone()).await,
            )
            .await?;
            println!("cancellation of {name} requested");
        }
        Command::Wait { name, timeout } => {
            let timeout = timeout.map(Duration::from_secs_f64);
            let operation = wait_until_done(&connection, &name, timeout).await?;
            print!("{}", describe_operation(&operation));
            if !operation.done {
                bail!(
                    "{name} is still running after {:.0} s",
                    timeout.unwrap_or_default().as_secs_f64()
                );
            }
            ensure_succeeded(&operation)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn packed<M: Message>(type_name: &str, message: &M) -> prost_types::Any {
        prost_types::Any {
            type_url: format!("type.googleapis.com/{type_name}"),
            value: message.encode_to_vec(),
        }
    }

    #[test]
    fn metadata_and_a_failure_are_decoded_from_the_operation() {
        let operation = longrunning::Operation {
            name: "operations/abc".into(),
            metadata: Some(packed(
                "spoofwatch.v1.JobMetadata",
                &v1::JobMetadata {
                    name: "operations/abc".into(),
                    kind: "training".into(),
                    state: v1::JobState::Failed as i32,
                    epoch: 2,
                    max_epochs: 30,
                    train_loss: 0.5,
                    val_loss: 0.25,
                    val_auroc: Some(0.875),
                    ..Default::default()
                },
            )),
            done: true,
            result: Some(OperationResult::Error(tonic_types::Status {
                code: tonic::Code::Cancelled as i32,
                message: "cancelled by the client".into(),
                details: Vec::new(),
            })),
        };
        let m = job_metadata(&operation).expect("metadata");
        assert_eq!(
            progress_line(&m),
            "failed epoch 2/30  loss 0.5000  val 0.2500  AUROC 0.8750"
        );
        let text = describe_operation(&operation);
        assert!(
            text.contains("error: CANCELLED: cancelled by the client"),
            "{text}"
        );
        let error = ensure_succeeded(&operation).expect_err("a failed job");
        assert!(error.to_string().contains("operations/abc did not succeed"));
    }

    #[test]
    fn a_training_result_names_the_model_and_its_metrics() {
        let result = v1::TrainingJobResult {
            model: Some(v1::Model {
                name: "models/m1".into(),
                ..Default::default()
            }),
            validation: Some(v1::Metrics {
                auroc: Some(0.9),
                ..Default::default()
            }),
            test: None,
            fleet_fit: None,
        };
        let operation = longrunning::Operation {
            name: "operations/x".into(),
            metadata: None,
            done: true,
            result: Some(OperationResult::Response(packed(
                "spoofwatch.v1.TrainingJobResult",
                &result,
            ))),
        };
        let text = describe_result(&operation).expect("done");
        assert!(text.contains("registered model:\nmodels/m1"), "{text}");
        assert!(text.contains("| validation | 0.9000 |"), "{text}");
        assert!(ensure_succeeded(&operation).is_ok());
    }

    #[test]
    fn timeouts_must_be_positive() {
        assert_eq!(parse_timeout("2.5"), Ok(2.5));
        assert!(parse_timeout("0").is_err());
        assert!(parse_timeout("soon").is_err());
    }
}
