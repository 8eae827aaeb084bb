//! `spoofwatch train --server URL --dataset …`: a training job on the server, followed with a
//! progress bar on a terminal (nothing into pipes); Ctrl-C offers to cancel it.

use std::io::{IsTerminal, Write};
use std::time::Duration;

use crate::connection::Connection;
use crate::error::{reply, rpc};
use crate::progress;
use crate::retry::{self, Idempotency};
use anyhow::{Result, bail};
use spoofwatch_proto::longrunning;
use spoofwatch_proto::v1;

use super::jobs::{describe_result, ensure_succeeded, progress_line, wait_until_done};
use crate::cli::flags::ProjectionArg;
use crate::cli::training_flags::{RemoteTrainingFlags, TrainingFlags};

/// How long to wait for a cancelled job to stop before giving up on showing its final state.
const CANCEL_WAIT: Duration = Duration::from_secs(30);

/// The job request these flags describe.
pub fn job_request(
    remote: &RemoteTrainingFlags,
    flags: &TrainingFlags,
) -> Result<v1::CreateTrainingJobRequest> {
    if remote.datasets.is_empty() {
        bail!("remote training needs at least one --dataset");
    }
    if !matches!(flags.projection, ProjectionArg::Wgs84) {
        bail!("--projection is not supported by remote training (the server uses wgs84)");
    }
    if let Some(flag) = [
        ("--no-exit-mask", flags.no_exit_mask),
        ("--no-vehicle-levels", flags.no_vehicle_levels),
        ("--timer-trust", flags.timer_trust),
        ("--rows-lifecycle", flags.rows_lifecycle),
    ]
    .into_iter()
    .find_map(|(name, set)| set.then_some(name))
    {
        bail!(
            "{flag} is an offline ablation, not supported by remote training (the server trains \
             the detector with its exit masking, per-vehicle levels, calibration trusted by its \
             uncertainty and lifecycle in seconds)"
        );
    }
    Ok(v1::CreateTrainingJobRequest {
        datasets: remote.datasets.clone(),
        validation_datasets: remote.val_datasets.clone(),
        spec: Some(v1::TrainingSpec {
            seed: flags.seed,
            max_epochs: flags.epochs,
            no_exchange: flags.no_exchange,
            no_third_order: flags.no_third_order,
            first_order_cell: flags.first_order_cell,
            features: flags.features.name().to_string(),
            select_kappa_rho: flags.select_kappa_rho,
            feature_schema: flags.schema.name().to_string(),
        }),
        display_name: remote.name.clone().unwrap_or_default(),
        activate: remote.activate,
        fleet_fit: None,
    })
}

/// Creates the job, follows it to the end and prints the registered model and its metrics.
pub async fn run(remote: RemoteTrainingFlags, flags: TrainingFlags) -> Result<()> {
    let request = job_request(&remote, &flags)?;
    run_job(&remote, request, flags.epochs).await
}

/// Creates the training (or fleet-fit) job `request`, follows it to the end and prints the
/// registered model, its metrics and a fit's report.
pub async fn run_job(
    remote: &RemoteTrainingFlags,
    request: v1::CreateTrainingJobRequest,
    max_epochs: u32,
) -> Result<()> {
    let Some(server) = remote.server.clone() else {
        bail!("remote training needs --server");
    };
    let options = remote.transport.options(remote.token.clone());
    let connection = Connection::connect_with(&server, &options).await?;
    let mut training = connection.training();
    // Not idempotent (a second job would train twice): retried only when refused.
    let operation = retry::unary(
        "creating the training job",
        Idempotency::NotIdempotent,
        async || training.create_training_job(request.clone()).await,
    )
    .await?;
    let name = operation.name.clone();
    println!("created training job {name}");
    match follow(&connection, &name, max_epochs).await? {
        Followed::Finished => {}
        Followed::LeftRunning => {
            println!(
                "{name} keeps running on the server; follow it with `spoofwatch jobs wait {name}` \
                 or `spoofwatch jobs get {name}`"
            );
            return Ok(());
        }
        Followed::CancelRequested => {
            let operation = wait_until_done(&connection, &name, Some(CANCEL_WAIT)).await?;
            if let Some(result) = describe_result(&operation) {
                print!("{result}");
            }
            bail!("training job {name} was cancelled");
        }
    }
    let request = longrunning::GetOperationRequest { name: name.clone() };
    let mut operations = connection.operations();
    let operation = retry::unary(
        format!("getting {name}"),
        Idempotency::Idempotent,
        async || operations.get_operation(request.clone()).await,
    )
    .await?;
    if let Some(result) = describe_result(&operation) {
        print!("{result}");
    }
    ensure_succeeded(&operation)
}

/// How following a job ended.
enum Followed {
    Finished,
    LeftRunning,
    CancelRequested,
}

/// Shows WatchJob progress until the job is done or the user interrupts.
async fn follow(connection: &Connection, name: &str, max_epochs: u32) -> Result<Followed> {
    let bar = progress::bar(u64::from(max_epochs), "training");
    // Without a bar but on a terminal (CI logs), one line per change; into a pipe, nothing.
    let lines = !progress::interactive() && progress::on_terminal();
    let request = v1::WatchJobRequest {
        name: name.to_string(),
    };
    let mut watch = reply(
        format!("watching {name}"),
        connection.training().watch_job(request),
    )
    .await?;
    let ctrl_c = tokio::signal::ctrl_c();
    tokio::pin!(ctrl_c);
    let mut last_line = String::new();
    loop {
        tokio::select! {
            message = watch.message() => match message.map_err(rpc(format!("watching {name}")))? {
                Some(m) => {
                    bar.set_length(u64::from(m.max_epochs.max(1)));
                    bar.set_position(u64::from(m.epoch));
                    let line = progress_line(&m);
                    bar.set_message(bar_message(&m));
                    if lines && line != last_line {
                        eprintln!("{name}: {line}");
                    }
                    last_line = line;
                }
                None => {
                    bar.finish_and_clear();
                    return Ok(Followed::Finished);
                }
            },
            _ = &mut ctrl_c => {
                bar.abandon();
                return on_interrupt(connection, name).await;
            }
        }
    }
}

/// The bar's short message (the bar itself shows the epoch): `loss 0.681 val 0.732 AUROC - ETA 21 s`.
fn bar_message(m: &v1::JobMetadata) -> String {
    let mut text = format!(
        "loss {:.3} val {:.3} AUROC {}",
        m.train_loss,
        m.val_loss,
        super::opt(m.val_auroc, 3)
    );
    if let Some(eta) = m.eta_s {
        text.push_str(&format!(" ETA {eta:.0} s"));
    }
    text
}

/// Ctrl-C while following: on a terminal ask whether to cancel; otherwise cancel.
async fn on_interrupt(connection: &Connection, name: &str) -> Result<Followed> {
    let terminal = std::io::stdin().is_terminal() && std::io::stderr().is_terminal();
    if terminal && !ask_yes_no(format!("\nCancel job {name}? [y/N] ")).await {
        return Ok(Followed::LeftRunning);
    }
    let request = longrunning::CancelOperationRequest {
        name: name.to_string(),
    };
    let mut operations = connection.operations();
    retry::unary(
        format!("cancelling {name}"),
        Idempotency::Idempotent,
        async || operations.cancel_operation(request.clone()).await,
    )
    .await?;
    eprintln!("cancellation of {name} requested");
    Ok(Followed::CancelRequested)
}

/// Asks on stderr and reads the answer on a separate thread (stdin reads block). A second Ctrl-C
/// counts as "no".
async fn ask_yes_no(question: String) -> bool {
    let (answer_tx, answer_rx) = tokio::sync::oneshot::channel();
    std::thread::spawn(move || {
        eprint!("{question}");
        let _ = std::io::stderr().flush();
        let mut line = String::new();
        let read = std::io::stdin().read_line(&mut line).is_ok();
        let _ = answer_tx.send(read && is_yes(&line));
    });
    tokio::select! {
        answer = answer_rx => answer.unwrap_or(false),
        _ = tokio::signal::ctrl_c() => false,
    }
}

/// `y` or `yes`, any case.
fn is_yes(answer: &str) -> bool {
    matches!(answer.trim().to_ascii_lowercase().as_str(), "y" | "yes")
}

#[cfg(test)]
mod tests {
    use super::*;
    use spoofwatch_core::model::FeatureGroups;

    fn remote(datasets: &[&str]) -> RemoteTrainingFlags {
        RemoteTrainingFlags {
            server: Some("http://127.0.0.1:1".into()),
            token: None,
            transport: Default::default(),
            datasets: datasets.iter().map(|s| s.to_string()).collect(),
            val_datasets: vec!["datasets/v".into()],
            activate: true,
            name: Some("run".into()),
        }
    }

    #[test]
    fn the_job_request_carries_the_model_flags() {
        let mut flags = TrainingFlags::defaults();
        flags.seed = 7;
        flags.epochs = 5;
        flags.no_third_order = true;
        flags.features = FeatureGroups::NoEvolutionNoQ;
        let request = job_request(&remote(&["datasets/a"]), &flags).expect("valid");
        let spec = request.spec.expect("spec");
        assert_eq!(
            (
                spec.seed,
                spec.max_epochs,
                spec.no_third_order,
                spec.no_exchange
            ),
            (7, 5, true, false)
        );
        assert_eq!(spec.features, "no-evolution-no-q");
        assert_eq!(request.datasets, vec!["datasets/a"]);
        assert_eq!(request.validation_datasets, vec!["datasets/v"]);
        assert!(request.activate);
        assert_eq!(request.display_name, "run");
    }

    #[test]
    fn remote_training_needs_a_dataset_and_the_default_projection() {
        let flags = TrainingFlags::defaults();
        assert!(job_request(&remote(&[]), &flags).is_err());
        let mut equirect = TrainingFlags::defaults();
        equirect.projection = ProjectionArg::Equirectangular;
        assert!(job_request(&remote(&["d"]), &equirect).is_err());
    }

    #[test]
    fn offline_ablations_are_refused_by_name_not_dropped() {
        for name in [
            "--no-exit-mask",
            "--no-vehicle-levels",
            "--timer-trust",
            "--rows-lifecycle",
        ] {
            let mut flags = TrainingFlags::defaults();
            match name {
                "--no-exit-mask" => flags.no_exit_mask = true,
                "--no-vehicle-levels" => flags.no_vehicle_levels = true,
                "--timer-trust" => flags.timer_trust = true,
                _ => flags.rows_lifecycle = true,
            }
            let error = job_request(&remote(&["d"]), &flags).expect_err(name);
            assert!(error.to_string().starts_with(name), "{error}");
        }
    }

    #[test]
    fn only_y_or_yes_confirms() {
        assert!(is_yes("y\n"));
        assert!(is_yes(" YES "));
        assert!(!is_yes("\n"));
        assert!(!is_yes("n"));
        assert!(!is_yes("yep"));
    }
}
