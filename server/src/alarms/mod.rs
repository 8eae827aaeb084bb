//! The alarm: its domain ([`event`]: it opens and ends, why it was raised, and the one place an
//! emitted event is counted and logged), its wire form ([`wire`]), and the alarm API: [`service`]
//! serves ListAlarms from the store and WatchAlarms from the stored event log, then from the live
//! [`feed`] of newly stored events (of every replica). Events the session outbox (`crate::outbox`)
//! has queued and not stored yet are not sent to watchers.
//!
//! Inside, each file uses only those listed before it: `event`, `wire`, `feed`, `service`. It
//! only reads the store: alarm events are written by the outbox, never here.

pub mod event;
pub mod feed;
pub mod service;
pub mod wire;
