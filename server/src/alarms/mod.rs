//! The alarm API: [`service`] serves ListAlarms from the store and WatchAlarms from the stored event
//! log, then from the live [`feed`] of newly stored events (of every replica). Events the session
//! outbox (`crate::outbox`) has queued and not stored yet are not sent to watchers. [`why`] maps an
//! alarm's explanation between the detector, the store and the wire.
//!
//! It only reads: alarm events are written by the outbox, never here.

pub mod feed;
pub mod service;
pub mod why;
