//! Training and evaluation jobs: their state machine, per-epoch history and final results.
//!
//! States: `queued → running → {succeeded, failed, cancelled}`, and `queued → {failed, cancelled}`.
//! Finished states are terminal. Cancellation is cooperative: [`Store::request_cancel`] only raises a
//! flag; the job's runner sees it and finishes the job as [`JobOutcome::Cancelled`].
//!
//! Ownership, for replicas sharing one database: a job belongs to the server instance that admitted
//! it ([`NewJob::owner`]), which runs it and refreshes its lease ([`Store::renew_job_leases`]) while
//! it is queued or running. [`Store::fail_abandoned_jobs`] fails the jobs whose owner is gone.

use serde_json::Value;
use sqlx::types::Json;

use super::error::{insert_error, require_finite};
use super::paging::PagePlan;
use super::{BackendKind, Page, PageRequest, Store, StoreError, now_unix_ms};

/// What a job does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobKind {
    /// Trains a new model.
    Training,
    /// Evaluates a model on a dataset.
    Evaluation,
}

impl JobKind {
    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            JobKind::Training => "training",
            JobKind::Evaluation => "evaluation",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        match name {
            "training" => Some(JobKind::Training),
            "evaluation" => Some(JobKind::Evaluation),
            _ => None,
        }
    }
}

text_enum!(JobKind);

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// A worker is running it.
    Running,
    /// Finished with a result.
    Succeeded,
    /// Finished with an error.
    Failed,
    /// Finished because cancellation was requested.
    Cancelled,
}

impl JobState {
    /// Whether the state is terminal (succeeded, failed or cancelled).
    pub fn is_finished(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }

    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        [
            JobState::Queued,
            JobState::Running,
            JobState::Succeeded,
            JobState::Failed,
            JobState::Cancelled,
        ]
        .into_iter()
        .find(|state| state.as_str() == name)
    }
}

text_enum!(JobState);

/// A job to enqueue; it starts `queued`.
#[derive(Debug, Clone, PartialEq)]
pub struct NewJob {
    /// Caller-chosen unique id (e.g. the operation name's suffix).
    pub id: String,
    /// What the job does.
    pub kind: JobKind,
    /// The request that created it, as the caller chooses to record it.
    pub request: Value,
    /// Initial progress metadata.
    pub metadata: Value,
    /// The server instance that admitted the job and will run it (see the module docs).
    pub owner: String,
}

/// The error a job ended with, as the store records it. The store keeps the code without
/// interpreting it: its callers choose it (the server's mapping of errors to codes is its own).
#[derive(Debug, Clone, PartialEq)]
pub struct JobEndError {
    /// The error code.
    pub code: i32,
    /// Human-readable reason.
    pub message: String,
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq)]
pub enum JobOutcome {
    /// Finished with a result (e.g. the trained model id and metrics).
    Succeeded {
        /// The result to record.
        result: Value,
    },
    /// Finished with an error.
    Failed(JobEndError),
    /// Stopped on request.
    Cancelled(JobEndError),
}

/// A stored job.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct JobRow {
    /// Unique id.
    pub id: String,
    /// What the job does.
    pub kind: JobKind,
    /// Where the job is in its life.
    pub state: JobState,
    /// The request that created it.
    #[sqlx(json, rename = "request_json")]
    pub request: Value,
    /// Latest progress metadata.
    #[sqlx(json, rename = "metadata_json")]
    pub metadata: Value,
    /// The result, once succeeded.
    #[sqlx(json(nullable), rename = "result_json")]
    pub result: Option<Value>,
    /// The [`JobEndError::code`], once failed or cancelled.
    pub error_code: Option<i32>,
    /// Reason, once failed or cancelled.
    pub error_message: Option<String>,
    /// Enqueue time, unix epoch milliseconds.
    #[sqlx(rename = "created_at")]
    pub created_at_ms: i64,
    /// When a worker started it, unix epoch milliseconds.
    #[sqlx(rename = "started_at")]
    pub started_at_ms: Option<i64>,
    /// When it finished, unix epoch milliseconds.
    #[sqlx(rename = "finished_at")]
    pub finished_at_ms: Option<i64>,
    /// Whether cancellation has been requested.
    pub cancel_requested: bool,
}

/// One epoch of a training job's history.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct EpochRow {
    /// Epoch number (unique per job).
    #[sqlx(try_from = "i64")]
    pub epoch: u32,
    /// Mean training loss.
    pub train_loss: f64,
    /// Validation loss.
    pub val_loss: f64,
    /// Validation AUROC, when the validation split had both classes.
    pub val_auroc: Option<f64>,
    /// Learning rate used in the epoch.
    pub learning_rate: f64,
    /// Seconds since the job started.
    pub elapsed_s: f64,
}

/// Which jobs [`Store::list_jobs`] returns; `None` fields do not filter.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct JobFilter {
    /// Only jobs of this kind.
    pub kind: Option<JobKind>,
    /// Only finished (`true`) or only queued/running (`false`) jobs.
    pub done: Option<bool>,
}

/// Listing name inside page tokens.
const LISTING: &str = "jobs";

const JOB_COLUMNS_BY_ID: &str = "SELECT id, kind, state, request_json, metadata_json, result_json, \
     error_code, error_message, created_at, started_at, finished_at, cancel_requested \
     FROM jobs WHERE id = $1";

/// The UPDATE of [`Store::fail_abandoned_jobs`], with `$lock` closing the row selection: on
/// PostgreSQL `FOR UPDATE SKIP LOCKED`, so a replica never waits for (nor fails) a job whose owner
/// is renewing its lease at this very moment, and concurrent sweeps never block each other.
macro_rules! fail_abandoned_sql {
    ($lock:literal) => {
        concat!(
            "UPDATE jobs SET state = 'failed', error_code = $1, error_message = $2, \
             finished_at = $3 WHERE id IN (SELECT id FROM jobs \
             WHERE state IN ('queued', 'running') \
             AND (owner IS NULL OR heartbeat_at IS NULL \
                  OR (owner = $5 AND $6) OR (owner <> $5 AND heartbeat_at < $4)) ",
            $lock,
            ")"
        )
    };
}

/// The job's current state inside the write transaction `$tx`; [`StoreError::NotFound`] if absent.
macro_rules! job_state {
    ($tx:ident, $id:expr) => {
        sqlx::query_scalar::<_, JobState>("SELECT state FROM jobs WHERE id = $1")
            .bind($id)
            .fetch_optional(&mut *$tx)
            .await?
            .ok_or_else(|| job_not_found($id))
    };
}

/// Runs, in one write transaction, the UPDATE `$sql` (binding the id as `$1`, then `$bind`s) on a
/// job whose current state `$allowed` accepts, and returns the updated row.
/// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] (naming `$action`) for
/// a state `$allowed` refuses. The binds are evaluated after the write lock is taken, so any time
/// they carry is the time of the change.
macro_rules! update_job {
    ($store:expr, $id:expr, $action:expr, $allowed:expr, $sql:expr $(, $bind:expr)* $(,)?) => {
        in_write_tx!($store, |tx| {
            let state = job_state!(tx, $id)?;
            if !($allowed)(state) {
                return Err(invalid_state($id, $action, state));
            }
            sqlx::query($sql)
                .bind($id)
                $(.bind($bind))*
                .execute(&mut *tx)
                .await?;
            let row = sqlx::query_as::<_, JobRow>(JOB_COLUMNS_BY_ID)
                .bind($id)
                .fetch_optional(&mut *tx)
                .await?
                .ok_or_else(|| job_not_found($id))?;
            tx.commit().await?;
            Ok(row)
        })
    };
}

impl Store {
    /// Enqueues a job in state `queued`, owned by `job.owner` with a fresh lease;
    /// [`StoreError::AlreadyExists`] if the id is taken.
    pub async fn insert_job(&self, job: NewJob) -> Result<JobRow, StoreError> {
        self.insert_job_at(job, now_unix_ms()).await
    }

    /// [`Store::insert_job`] with an explicit creation time (tests pin ordering with it).
    pub(crate) async fn insert_job_at(
        &self,
        job: NewJob,
        created_at_ms: i64,
    ) -> Result<JobRow, StoreError> {
        let inserted = on_pool!(self, |pool| {
            sqlx::query(
                "INSERT INTO jobs (id, kind, state, request_json, metadata_json, created_at, \
                 cancel_requested, owner, heartbeat_at) \
                 VALUES ($1, $2, 'queued', $3, $4, $5, FALSE, $6, $7)",
            )
            .bind(&job.id)
            .bind(job.kind)
            .bind(Json(&job.request))
            .bind(Json(&job.metadata))
            .bind(created_at_ms)
            .bind(&job.owner)
            .bind(now_unix_ms())
            .execute(pool)
            .await
            .map(drop)
        });
        match inserted {
            Ok(_) => Ok(JobRow {
                id: job.id,
                kind: job.kind,
                state: JobState::Queued,
                request: job.request,
                metadata: job.metadata,
                result: None,
                error_code: None,
                error_message: None,
                created_at_ms,
                started_at_ms: None,
                finished_at_ms: None,
                cancel_requested: false,
            }),
            Err(error) => Err(insert_error(error, "job", &job.id)),
        }
    }

    /// The job with this id.
    pub async fn get_job(&self, id: &str) -> Result<Option<JobRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, JobRow>(JOB_COLUMNS_BY_ID)
                .bind(id)
                .fetch_optional(pool)
                .await?
        }))
    }

    /// The job's epoch history in epoch order (empty for an unknown job or one without epochs).
    pub async fn job_epochs(&self, id: &str) -> Result<Vec<EpochRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, EpochRow>(
                "SELECT epoch, train_loss, val_loss, val_auroc, learning_rate, elapsed_s \
                 FROM job_epochs WHERE job_id = $1 ORDER BY epoch",
            )
            .bind(id)
            .fetch_all(pool)
            .await?
        }))
    }

    /// One page of jobs matching `filter`, newest first.
    ///
    /// Fails with [`StoreError::InvalidPageToken`] for a token not issued by this listing.
    pub async fn list_jobs(
        &self,
        filter: &JobFilter,
        request: &PageRequest,
    ) -> Result<Page<JobRow>, StoreError> {
        let plan = PagePlan::new(LISTING, request)?;
        let rows = on_pool!(self, |pool| {
            sqlx::query_as::<_, JobRow>(
                "SELECT id, kind, state, request_json, metadata_json, result_json, error_code, \
                 error_message, created_at, started_at, finished_at, cancel_requested FROM jobs \
                 WHERE ($1 IS NULL OR kind = $1) \
                 AND ($2 IS NULL OR (state IN ('succeeded', 'failed', 'cancelled')) = $2) \
                 AND ($3 IS NULL OR (created_at, id) < ($3, $4)) \
                 ORDER BY created_at DESC, id DESC LIMIT $5",
            )
            .bind(filter.kind)
            .bind(filter.done)
            .bind(plan.after_created_at())
            .bind(plan.after_id())
            .bind(plan.fetch_limit())
            .fetch_all(pool)
            .await?
        });
        Ok(plan.finish(LISTING, rows, |row: &JobRow| {
            (row.created_at_ms, row.id.as_str())
        }))
    }

    /// Moves a queued job to `running`, records its start time and renews its lease.
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] unless it is queued.
    pub async fn mark_running(&self, id: &str) -> Result<JobRow, StoreError> {
        let queued = |state| state == JobState::Queued;
        update_job!(
            self,
            id,
            "mark running",
            queued,
            "UPDATE jobs SET state = 'running', started_at = $2, heartbeat_at = $2 WHERE id = $1",
            now_unix_ms(),
        )
    }

    /// Records one epoch of a running job.
    ///
    /// [`StoreError::NotFound`] for an unknown job, [`StoreError::InvalidState`] unless it is running,
    /// [`StoreError::AlreadyExists`] if this epoch was recorded, [`StoreError::InvalidValue`] for a
    /// non-finite number.
    pub async fn append_epoch(&self, id: &str, epoch: &EpochRow) -> Result<(), StoreError> {
        validate_epoch(epoch)?;
        in_write_tx!(self, |tx| {
            let state = job_state!(tx, id)?;
            if state != JobState::Running {
                return Err(invalid_state(id, "append an epoch to", state));
            }
            let inserted = sqlx::query(
                "INSERT INTO job_epochs (job_id, epoch, train_loss, val_loss, val_auroc, \
                 learning_rate, elapsed_s) VALUES ($1, $2, $3, $4, $5, $6, $7)",
            )
            .bind(id)
            .bind(i64::from(epoch.epoch))
            .bind(epoch.train_loss)
            .bind(epoch.val_loss)
            .bind(epoch.val_auroc)
            .bind(epoch.learning_rate)
            .bind(epoch.elapsed_s)
            .execute(&mut *tx)
            .await;
            inserted
                .map_err(|error| insert_error(error, "epoch", &format!("{id}/{}", epoch.epoch)))?;
            tx.commit().await?;
            Ok(())
        })
    }

    /// Replaces the job's progress metadata (any state); [`StoreError::NotFound`] for an unknown id.
    pub async fn update_job_metadata(&self, id: &str, metadata: &Value) -> Result<(), StoreError> {
        let updated = on_pool!(self, |pool| {
            sqlx::query("UPDATE jobs SET metadata_json = $2 WHERE id = $1")
                .bind(id)
                .bind(Json(metadata))
                .execute(pool)
                .await?
                .rows_affected()
        });
        if updated == 0 {
            return Err(job_not_found(id));
        }
        Ok(())
    }

    /// Finishes a queued or running job with `outcome` and records the finish time.
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] if already finished.
    pub async fn finish_job(&self, id: &str, outcome: JobOutcome) -> Result<JobRow, StoreError> {
        let (state, result, error) = match outcome {
            JobOutcome::Succeeded { result } => (JobState::Succeeded, Some(result), None),
            JobOutcome::Failed(error) => (JobState::Failed, None, Some(error)),
            JobOutcome::Cancelled(error) => (JobState::Cancelled, None, Some(error)),
        };
        let code = error.as_ref().map(|error| error.code);
        let message = error.map(|error| error.message);
        let unfinished = |state: JobState| !state.is_finished();
        update_job!(
            self,
            id,
            "finish",
            unfinished,
            "UPDATE jobs SET state = $2, result_json = $3, error_code = $4, \
             error_message = $5, finished_at = $6 WHERE id = $1",
            state,
            result.map(Json),
            code,
            message,
            now_unix_ms(),
        )
    }

    /// Flags a queued or running job for cancellation (idempotent); its runner finishes it.
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::InvalidState`] if already finished.
    pub async fn request_cancel(&self, id: &str) -> Result<JobRow, StoreError> {
        let unfinished = |state: JobState| !state.is_finished();
        update_job!(
            self,
            id,
            "cancel",
            unfinished,
            "UPDATE jobs SET cancel_requested = TRUE WHERE id = $1",
        )
    }

    /// Deletes a finished job and its epochs.
    ///
    /// [`StoreError::NotFound`] for an unknown id, [`StoreError::JobNotFinished`] if queued or running.
    pub async fn delete_job(&self, id: &str) -> Result<(), StoreError> {
        in_write_tx!(self, |tx| {
            let state = job_state!(tx, id)?;
            if !state.is_finished() {
                return Err(StoreError::JobNotFinished {
                    id: id.to_owned(),
                    state: state.as_str(),
                });
            }
            sqlx::query("DELETE FROM jobs WHERE id = $1")
                .bind(id)
                .execute(&mut *tx)
                .await?;
            tx.commit().await?;
            Ok(())
        })
    }

    /// Renews the lease of every queued or running job `owner` holds (its heartbeat, at wall time
    /// `now_ms`) and returns them with their cancel flag: the owner cancels those flagged through
    /// another replica, and stops those no longer listed (finished elsewhere).
    pub async fn renew_job_leases(
        &self,
        owner: &str,
        now_ms: i64,
    ) -> Result<Vec<(String, bool)>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, (String, bool)>(
                "UPDATE jobs SET heartbeat_at = $2 \
                 WHERE owner = $1 AND state IN ('queued', 'running') \
                 RETURNING id, cancel_requested",
            )
            .bind(owner)
            .bind(now_ms)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Recovery: every queued or running job whose owner is gone becomes `failed` with `error`, since
    /// no worker survives its server. A job's owner is gone when its lease was last renewed before
    /// `lease_cutoff_ms`, when it has no owner (stored before owners were), and, with `restarting`,
    /// when the owner is `instance` itself: its jobs are from an earlier run of this instance. Jobs
    /// of `instance` are never failed otherwise. Returns how many jobs were failed.
    pub async fn fail_abandoned_jobs(
        &self,
        error: &JobEndError,
        instance: &str,
        restarting: bool,
        lease_cutoff_ms: i64,
    ) -> Result<u64, StoreError> {
        let sql = match self.kind() {
            BackendKind::Sqlite => fail_abandoned_sql!(""),
            BackendKind::Postgres => fail_abandoned_sql!("FOR UPDATE SKIP LOCKED"),
        };
        Ok(on_pool!(self, |pool| {
            sqlx::query(sql)
                .bind(error.code)
                .bind(&error.message)
                .bind(now_unix_ms())
                .bind(lease_cutoff_ms)
                .bind(instance)
                .bind(restarting)
                .execute(pool)
                .await?
                .rows_affected()
        }))
    }
}

fn job_not_found(id: &str) -> StoreError {
    StoreError::NotFound {
        kind: "job",
        id: id.to_owned(),
    }
}

fn invalid_state(id: &str, action: &'static str, state: JobState) -> StoreError {
    StoreError::InvalidState {
        kind: "job",
        id: id.to_owned(),
        action,
        state: state.as_str(),
    }
}

/// SQLite stores NaN as NULL; reject non-finite numbers with a precise error instead.
fn validate_epoch(epoch: &EpochRow) -> Result<(), StoreError> {
    require_finite("train_loss", epoch.train_loss)?;
    require_finite("val_loss", epoch.val_loss)?;
    if let Some(auroc) = epoch.val_auroc {
        require_finite("val_auroc", auroc)?;
    }
    require_finite("learning_rate", epoch.learning_rate)?;
    require_finite("elapsed_s", epoch.elapsed_s)?;
    Ok(())
}
