//! Jobs: state machine, epochs, listing with filters, deletion and restart recovery.

use serde_json::json;

use super::{count_rows, new_job};
use crate::jobs::JobFailure;
use crate::store::{
    EpochRow, JobEndError, JobFilter, JobKind, JobOutcome, JobState, PageRequest, Store,
    StoreError, now_unix_ms,
};

fn epoch(number: u32) -> EpochRow {
    EpochRow {
        epoch: number,
        train_loss: 0.5 / f64::from(number + 1),
        val_loss: 0.6 / f64::from(number + 1),
        val_auroc: if number == 0 { None } else { Some(0.9) },
        learning_rate: 1e-3,
        elapsed_s: 2.5 * f64::from(number + 1),
    }
}

/// The error the server records for `failure`, with the message `message`.
fn recorded(failure: JobFailure, message: &str) -> JobEndError {
    JobEndError {
        message: message.to_owned(),
        ..JobEndError::from(failure)
    }
}

async fn running_job(store: &Store, id: &str) {
    store
        .insert_job(new_job(id, JobKind::Training))
        .await
        .unwrap();
    store.mark_running(id).await.unwrap();
}

async fn insert_then_get_round_trips_a_queued_job(store: Store) {
    let inserted = store
        .insert_job_at(new_job("j1", JobKind::Evaluation), 77)
        .await
        .unwrap();
    let fetched = store.get_job("j1").await.unwrap().expect("job exists");
    assert_eq!(fetched, inserted);
    assert_eq!(fetched.kind, JobKind::Evaluation);
    assert_eq!(fetched.state, JobState::Queued);
    assert_eq!(fetched.request, json!({"dataset": "d1", "epochs": 5}));
    assert_eq!(fetched.metadata, json!({"epoch": 0}));
    assert_eq!(fetched.result, None);
    assert_eq!(
        (fetched.error_code, fetched.error_message.as_deref()),
        (None, None)
    );
    assert_eq!(fetched.created_at_ms, 77);
    assert_eq!(
        (fetched.started_at_ms, fetched.finished_at_ms),
        (None, None)
    );
    assert!(!fetched.cancel_requested);
    assert_eq!(store.get_job("nope").await.unwrap(), None);
}

async fn duplicate_job_id_is_refused(store: Store) {
    store
        .insert_job(new_job("j1", JobKind::Training))
        .await
        .unwrap();
    let error = store
        .insert_job(new_job("j1", JobKind::Evaluation))
        .await
        .unwrap_err();
    assert!(
        matches!(&error, StoreError::AlreadyExists { kind: "job", id } if id == "j1"),
        "{error:?}"
    );
    let kept = store.get_job("j1").await.unwrap().expect("original kept");
    assert_eq!(kept.kind, JobKind::Training);
}

async fn job_runs_records_epochs_and_succeeds_once(store: Store) {
    store
        .insert_job(new_job("j1", JobKind::Training))
        .await
        .unwrap();
    let running = store.mark_running("j1").await.unwrap();
    assert_eq!(running.state, JobState::Running);
    assert!(running.started_at_ms.is_some());

    for number in 0..3 {
        store.append_epoch("j1", &epoch(number)).await.unwrap();
    }
    store
        .update_job_metadata("j1", &json!({"epoch": 3, "eta_s": 12.5}))
        .await
        .unwrap();
    assert_eq!(
        store.job_epochs("j1").await.unwrap(),
        vec![epoch(0), epoch(1), epoch(2)]
    );

    let result = json!({"model_id": "m-new", "val_auroc": 0.91});
    let finished = store
        .finish_job(
            "j1",
            JobOutcome::Succeeded {
                result: result.clone(),
            },
        )
        .await
        .unwrap();
    assert_eq!(finished.state, JobState::Succeeded);
    assert_eq!(finished.result, Some(result));
    assert_eq!(finished.metadata, json!({"epoch": 3, "eta_s": 12.5}));
    assert_eq!(
        (finished.error_code, finished.error_message.as_deref()),
        (None, None)
    );
    let finished_at = finished.finished_at_ms.expect("finish time recorded");
    assert!(finished_at >= running.started_at_ms.expect("started"));
    assert_eq!(store.get_job("j1").await.unwrap(), Some(finished.clone()));

    // Finished is terminal: finishing again, cancelling or restarting are refused and change nothing.
    let again = store
        .finish_job(
            "j1",
            JobOutcome::Failed(JobEndError {
                code: 13,
                message: "late".to_owned(),
            }),
        )
        .await
        .unwrap_err();
    assert!(
        matches!(
            &again,
            StoreError::InvalidState { kind: "job", action: "finish", state: "succeeded", id } if id == "j1"
        ),
        "{again:?}"
    );
    assert_eq!(again.to_string(), "cannot finish job 'j1': it is succeeded");
    assert!(matches!(
        store.request_cancel("j1").await,
        Err(StoreError::InvalidState {
            action: "cancel",
            ..
        })
    ));
    assert!(matches!(
        store.mark_running("j1").await,
        Err(StoreError::InvalidState {
            action: "mark running",
            ..
        })
    ));
    assert!(matches!(
        store.append_epoch("j1", &epoch(3)).await,
        Err(StoreError::InvalidState { .. })
    ));
    assert_eq!(store.get_job("j1").await.unwrap(), Some(finished));
    assert_eq!(store.job_epochs("j1").await.unwrap().len(), 3);
}

async fn mark_running_twice_is_refused(store: Store) {
    running_job(&store, "j1").await;
    let error = store.mark_running("j1").await.unwrap_err();
    assert!(
        matches!(
            error,
            StoreError::InvalidState {
                state: "running",
                ..
            }
        ),
        "{error:?}"
    );
    assert!(matches!(
        store.mark_running("nope").await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
}

async fn failed_and_cancelled_outcomes_record_code_and_message(store: Store) {
    running_job(&store, "failing").await;
    let failed = store
        .finish_job(
            "failing",
            JobOutcome::Failed(JobEndError {
                code: 3,
                message: "dataset has no spoofed rows".to_owned(),
            }),
        )
        .await
        .unwrap();
    assert_eq!(failed.state, JobState::Failed);
    assert_eq!(failed.error_code, Some(3));
    assert_eq!(
        failed.error_message.as_deref(),
        Some("dataset has no spoofed rows")
    );
    assert_eq!(failed.result, None);

    // A queued job can be cancelled before it ever runs.
    store
        .insert_job(new_job("queued", JobKind::Evaluation))
        .await
        .unwrap();
    let flagged = store.request_cancel("queued").await.unwrap();
    assert!(flagged.cancel_requested);
    assert_eq!(flagged.state, JobState::Queued);
    assert!(
        store
            .request_cancel("queued")
            .await
            .unwrap()
            .cancel_requested
    );
    let cancelled = store
        .finish_job(
            "queued",
            JobOutcome::Cancelled(recorded(JobFailure::Cancelled, "cancelled by user")),
        )
        .await
        .unwrap();
    assert_eq!(cancelled.state, JobState::Cancelled);
    assert_eq!(cancelled.error_code, Some(tonic::Code::Cancelled as i32));
    assert_eq!(
        cancelled.error_message.as_deref(),
        Some("cancelled by user")
    );
    assert_eq!(cancelled.started_at_ms, None);
}

async fn unknown_job_operations_are_not_found(store: Store) {
    let outcome = JobOutcome::Succeeded { result: json!({}) };
    assert!(matches!(
        store.finish_job("nope", outcome).await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
    assert!(matches!(
        store.request_cancel("nope").await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
    assert!(matches!(
        store.append_epoch("nope", &epoch(0)).await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
    assert!(matches!(
        store.update_job_metadata("nope", &json!({})).await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
    assert!(matches!(
        store.delete_job("nope").await,
        Err(StoreError::NotFound { kind: "job", .. })
    ));
    assert_eq!(store.job_epochs("nope").await.unwrap(), vec![]);
}

async fn epochs_need_a_running_job_unique_numbers_and_finite_values(store: Store) {
    store
        .insert_job(new_job("j1", JobKind::Training))
        .await
        .unwrap();
    let error = store.append_epoch("j1", &epoch(0)).await.unwrap_err();
    assert!(
        matches!(
            error,
            StoreError::InvalidState {
                state: "queued",
                ..
            }
        ),
        "{error:?}"
    );

    store.mark_running("j1").await.unwrap();
    store.append_epoch("j1", &epoch(0)).await.unwrap();
    let error = store.append_epoch("j1", &epoch(0)).await.unwrap_err();
    assert!(
        matches!(&error, StoreError::AlreadyExists { kind: "epoch", id } if id == "j1/0"),
        "{error:?}"
    );

    let mut diverged = epoch(1);
    diverged.train_loss = f64::NAN;
    let error = store.append_epoch("j1", &diverged).await.unwrap_err();
    assert!(
        matches!(
            error,
            StoreError::InvalidValue {
                field: "train_loss",
                ..
            }
        ),
        "{error:?}"
    );
    let mut bad_auroc = epoch(1);
    bad_auroc.val_auroc = Some(f64::INFINITY);
    assert!(matches!(
        store.append_epoch("j1", &bad_auroc).await,
        Err(StoreError::InvalidValue {
            field: "val_auroc",
            ..
        })
    ));
    assert_eq!(store.job_epochs("j1").await.unwrap(), vec![epoch(0)]);
}

async fn unfinished_jobs_cannot_be_deleted_and_finished_ones_cascade(store: Store) {
    store
        .insert_job(new_job("queued", JobKind::Training))
        .await
        .unwrap();
    running_job(&store, "running").await;
    store.append_epoch("running", &epoch(0)).await.unwrap();

    for (id, state) in [("queued", "queued"), ("running", "running")] {
        let error = store.delete_job(id).await.unwrap_err();
        assert!(
            matches!(&error, StoreError::JobNotFinished { id: got, state: s } if got == id && *s == state),
            "{error:?}"
        );
    }
    assert_eq!(count_rows(&store, "jobs").await, 2);

    store
        .finish_job("running", JobOutcome::Succeeded { result: json!({}) })
        .await
        .unwrap();
    store.delete_job("running").await.unwrap();
    assert_eq!(store.get_job("running").await.unwrap(), None);
    assert_eq!(count_rows(&store, "job_epochs").await, 0);
    assert_eq!(count_rows(&store, "jobs").await, 1);
}

async fn a_restart_fails_its_own_and_ownerless_jobs_but_not_live_replicas_ones(store: Store) {
    store
        .insert_job(new_job("queued", JobKind::Training))
        .await
        .unwrap();
    running_job(&store, "running").await;
    running_job(&store, "done").await;
    let done = store
        .finish_job(
            "done",
            JobOutcome::Succeeded {
                result: json!({"ok": true}),
            },
        )
        .await
        .unwrap();
    let mut other = new_job("other-replica", JobKind::Training);
    other.owner = "other-server".to_owned();
    store.insert_job(other).await.unwrap();
    store
        .execute_for_test("UPDATE jobs SET owner = NULL, heartbeat_at = NULL WHERE id = 'queued'")
        .await;

    let reason = "server restarted while the job was running";
    let cutoff = now_unix_ms() - 30_000;
    let abandoned = recorded(JobFailure::Abandoned, reason);
    let failed = store.fail_abandoned_jobs(&abandoned, "this-server", true, cutoff);
    assert_eq!(
        failed.await.unwrap(),
        2,
        "its own running job and the ownerless queued one"
    );
    for id in ["queued", "running"] {
        let job = store.get_job(id).await.unwrap().expect("job kept");
        assert_eq!(job.state, JobState::Failed, "{id}");
        assert_eq!(job.error_code, Some(10), "{id}");
        assert_eq!(job.error_message.as_deref(), Some(reason), "{id}");
        assert!(job.finished_at_ms.is_some(), "{id}");
    }
    assert_eq!(store.get_job("done").await.unwrap(), Some(done));
    let live = store.get_job("other-replica").await.unwrap().expect("kept");
    assert_eq!(
        live.state,
        JobState::Queued,
        "a live replica's job is left alone"
    );
    // Nothing is left to fail the second time.
    let again = store.fail_abandoned_jobs(&abandoned, "this-server", true, cutoff);
    assert_eq!(again.await.unwrap(), 0);
}

async fn jobs_whose_lease_expired_are_failed_by_other_servers_only(store: Store) {
    for (id, owner) in [("mine", "this-server"), ("theirs", "other-server")] {
        let mut job = new_job(id, JobKind::Evaluation);
        job.owner = owner.to_owned();
        store.insert_job(job).await.unwrap();
    }
    store.request_cancel("theirs").await.unwrap();
    // Both leases were last renewed a minute ago.
    let long_ago = now_unix_ms() - 60_000;
    assert_eq!(
        store
            .renew_job_leases("this-server", long_ago)
            .await
            .unwrap(),
        vec![("mine".to_owned(), false)]
    );
    assert_eq!(
        store
            .renew_job_leases("other-server", long_ago)
            .await
            .unwrap(),
        vec![("theirs".to_owned(), true)],
        "the owner learns of a cancellation requested anywhere"
    );

    let cutoff = now_unix_ms() - 30_000;
    let abandoned = recorded(JobFailure::Abandoned, "gone");
    let failed = store.fail_abandoned_jobs(&abandoned, "this-server", false, cutoff);
    assert_eq!(failed.await.unwrap(), 1);
    let theirs = store.get_job("theirs").await.unwrap().expect("kept");
    assert_eq!(
        (theirs.state, theirs.error_code),
        (JobState::Failed, Some(10))
    );
    let mine = store.get_job("mine").await.unwrap().expect("kept");
    assert_eq!(
        mine.state,
        JobState::Queued,
        "a server never fails its own live jobs"
    );
    assert_eq!(
        store
            .renew_job_leases("other-server", now_unix_ms())
            .await
            .unwrap(),
        vec![],
        "a failed job is no longer the owner's"
    );

    // A renewed lease protects a job from everyone else.
    store
        .renew_job_leases("this-server", now_unix_ms())
        .await
        .unwrap();
    let failed = store.fail_abandoned_jobs(&abandoned, "other-server", false, cutoff);
    assert_eq!(failed.await.unwrap(), 0);
}

async fn list_jobs_filters_by_kind_and_done_and_pages_newest_first(store: Store) {
    let jobs = [
        ("t1", JobKind::Training, 10),
        ("e1", JobKind::Evaluation, 20),
        ("t2", JobKind::Training, 30),
        ("t3", JobKind::Training, 40),
        ("e2", JobKind::Evaluation, 50),
    ];
    for (id, kind, created_at) in jobs {
        store
            .insert_job_at(new_job(id, kind), created_at)
            .await
            .unwrap();
    }
    store
        .finish_job("t1", JobOutcome::Succeeded { result: json!({}) })
        .await
        .unwrap();
    store
        .finish_job(
            "e2",
            JobOutcome::Cancelled(recorded(JobFailure::Cancelled, "stop")),
        )
        .await
        .unwrap();
    store.mark_running("t3").await.unwrap();

    let ids = |filter: JobFilter| {
        let store = store.clone();
        async move {
            let page = store
                .list_jobs(&filter, &PageRequest::first(100))
                .await
                .unwrap();
            page.items.into_iter().map(|j| j.id).collect::<Vec<_>>()
        }
    };
    assert_eq!(
        ids(JobFilter::default()).await,
        ["e2", "t3", "t2", "e1", "t1"]
    );
    let training = JobFilter {
        kind: Some(JobKind::Training),
        done: None,
    };
    assert_eq!(ids(training).await, ["t3", "t2", "t1"]);
    let done = JobFilter {
        kind: None,
        done: Some(true),
    };
    assert_eq!(ids(done).await, ["e2", "t1"]);
    let unfinished_training = JobFilter {
        kind: Some(JobKind::Training),
        done: Some(false),
    };
    assert_eq!(ids(unfinished_training).await, ["t3", "t2"]);

    // Pagination composes with the filter.
    let first = store
        .list_jobs(&training, &PageRequest::first(2))
        .await
        .unwrap();
    assert_eq!(first.items.len(), 2);
    let token = first.next_page_token.expect("third training job");
    let second = store
        .list_jobs(&training, &PageRequest::after(2, token))
        .await
        .unwrap();
    let second_ids: Vec<_> = second.items.iter().map(|j| j.id.as_str()).collect();
    assert_eq!(second_ids, ["t1"]);
    assert_eq!(second.next_page_token, None);
    assert!(matches!(
        store
            .list_jobs(&training, &PageRequest::after(2, "nothex"))
            .await,
        Err(StoreError::InvalidPageToken)
    ));
}

on_both_backends!(
    insert_then_get_round_trips_a_queued_job,
    duplicate_job_id_is_refused,
    job_runs_records_epochs_and_succeeds_once,
    mark_running_twice_is_refused,
    failed_and_cancelled_outcomes_record_code_and_message,
    unknown_job_operations_are_not_found,
    epochs_need_a_running_job_unique_numbers_and_finite_values,
    unfinished_jobs_cannot_be_deleted_and_finished_ones_cascade,
    a_restart_fails_its_own_and_ownerless_jobs_but_not_live_replicas_ones,
    jobs_whose_lease_expired_are_failed_by_other_servers_only,
    list_jobs_filters_by_kind_and_done_and_pages_newest_first,
);
