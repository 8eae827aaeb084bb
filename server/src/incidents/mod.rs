//! Area incidents on the server: the [`correlator`] loop (one server of a database at a time, by
//! lease) turns the fleet's stored alarms into incidents with the core's correlator and stores
//! them; [`service`] serves ListIncidents, GetIncident and WatchIncidents from the store and the
//! incident event log, and EndIncident (an admin's end of an incident); [`areas`] holds the open incidents' areas that the sessions score with (the
//! area prior); [`settings`] is how this server correlates them.
//!
//! Alarms reach it only through the store (every replica's alarm event log), never from the
//! detection path.

pub mod areas;
pub mod correlator;
pub mod service;
pub mod settings;
