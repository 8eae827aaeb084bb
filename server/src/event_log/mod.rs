//! Following a stored event log (alarm events, incident events): one live [`feed`] per server that
//! broadcasts each newly stored event, and the resumable [`watch`] behind WatchAlarms and
//! WatchIncidents, with one cursor semantics for both.
//!
//! A log is described by [`EventLog`]: how its events are read from the store, their positions
//! (assigned by the database in commit order, across every replica) and their wire messages.
//!
//! It owns the following and the replay; it must not write events (the session outbox and the
//! incident correlator do) nor know what an event means.

use std::future::Future;

use crate::store::{Store, StoreError};

pub mod feed;
pub mod watch;

/// A log of stored events with positions 1, 2, 3, … in commit order.
pub trait EventLog: Send + Sync + 'static {
    /// A stored event.
    type Event: Send + Sync + 'static;
    /// What a watcher asks for beyond the whole log (a vehicle); `()` when nothing.
    type Filter: Send + Sync + 'static;
    /// An event, or CAUGHT_UP, on the wire.
    type Message: Send + 'static;
    /// What the events are, for logs and messages ("alarm", "incident").
    const NAME: &'static str;
    /// Where a caller learns what is stored when its cursor is refused ("ListAlarms").
    const LISTING_RPC: &'static str;

    fn position(event: &Self::Event) -> i64;

    /// The events with `after < position <= through` that `filter` wants (all without one), in
    /// position order, at most `limit`.
    fn read(
        store: &Store,
        after: i64,
        through: i64,
        filter: Option<&Self::Filter>,
        limit: u32,
    ) -> impl Future<Output = Result<Vec<Self::Event>, StoreError>> + Send;

    /// The latest position (0 for an empty log).
    fn latest(store: &Store) -> impl Future<Output = Result<i64, StoreError>> + Send;

    /// Whether a watcher with `filter` is sent `event`.
    fn wanted(filter: Option<&Self::Filter>, event: &Self::Event) -> bool;

    fn message(event: &Self::Event) -> Self::Message;

    /// The CAUGHT_UP message at `cursor`.
    fn caught_up(cursor: i64) -> Self::Message;
}
