//! A paced replay's delivery over time: of the samples due in each interval (by
//! [`crate::replay::batch_due_times`]), how many got a detection, how many before the vehicle's
//! next batch was due, and the latency percentiles (from when a batch was due, so a failover's
//! wait and its resends count against the interval the samples were due in).
//!
//! Pure arithmetic on what it is given: no I/O, no clocks.

use std::time::Duration;

use serde::Serialize;

/// The `q`-quantile (0–1) of sorted values by the nearest-rank method.
pub fn percentile(sorted: &[Duration], q: f64) -> Option<Duration> {
    if sorted.is_empty() {
        return None;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    Some(sorted[rank.clamp(1, sorted.len()) - 1])
}

/// Samples due and detections received, interval by interval.
#[derive(Clone, Debug)]
pub struct Timeline {
    every: Duration,
    /// A detection within this latency was on time.
    on_time_within: Duration,
    due: Vec<u64>,
    latencies: Vec<Vec<Duration>>,
}

/// One interval of a [`Timeline`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TimelineRow {
    /// The interval, in seconds from the replay's start.
    pub start_s: f64,
    pub end_s: f64,
    /// Samples due in it.
    pub due: u64,
    /// Of those, samples that got a detection (at any time).
    pub delivered: u64,
    /// Of those, detections within the on-time limit.
    pub on_time: u64,
    /// Latency percentiles of the delivered samples, in milliseconds (`None` without any).
    pub p50_ms: Option<f64>,
    pub p99_ms: Option<f64>,
    pub max_ms: Option<f64>,
}

impl TimelineRow {
    /// Delivered samples as a percentage of those due (100 with none due).
    pub fn delivered_pct(&self) -> f64 {
        percentage(self.delivered, self.due)
    }

    /// On-time samples as a percentage of those due (100 with none due).
    pub fn on_time_pct(&self) -> f64 {
        percentage(self.on_time, self.due)
    }
}

fn percentage(part: u64, whole: u64) -> f64 {
    if whole == 0 {
        100.0
    } else {
        100.0 * part as f64 / whole as f64
    }
}

impl Timeline {
    /// Intervals of `every` (> 0); a detection is on time within `on_time_within`.
    pub fn new(every: Duration, on_time_within: Duration) -> Self {
        assert!(!every.is_zero(), "a timeline's interval must be positive");
        Self {
            every,
            on_time_within,
            due: Vec::new(),
            latencies: Vec::new(),
        }
    }

    fn interval(&mut self, at: Duration) -> usize {
        let index = (at.as_secs_f64() / self.every.as_secs_f64()) as usize;
        if index >= self.due.len() {
            self.due.resize(index + 1, 0);
            self.latencies.resize_with(index + 1, Vec::new);
        }
        index
    }

    /// `samples` samples fell due at `due` (from the replay's start).
    pub fn add_due(&mut self, due: Duration, samples: usize) {
        let index = self.interval(due);
        self.due[index] += samples as u64;
    }

    /// A sample due at `due` got its detection `latency` later.
    pub fn add_delivered(&mut self, due: Duration, latency: Duration) {
        let index = self.interval(due);
        self.latencies[index].push(latency);
    }

    /// The intervals, in order.
    pub fn rows(&self) -> Vec<TimelineRow> {
        let ms = |d: Option<Duration>| d.map(|d| d.as_secs_f64() * 1e3);
        (0..self.due.len())
            .map(|index| {
                let mut latencies = self.latencies[index].clone();
                latencies.sort_unstable();
                let start_s = index as f64 * self.every.as_secs_f64();
                TimelineRow {
                    start_s,
                    end_s: start_s + self.every.as_secs_f64(),
                    due: self.due[index],
                    delivered: latencies.len() as u64,
                    on_time: latencies.partition_point(|l| *l <= self.on_time_within) as u64,
                    p50_ms: ms(percentile(&latencies, 0.50)),
                    p99_ms: ms(percentile(&latencies, 0.99)),
                    max_ms: ms(latencies.last().copied()),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let values: Vec<Duration> = (1..=100).map(ms).collect();
        assert_eq!(percentile(&values, 0.50), Some(ms(50)));
        assert_eq!(percentile(&values, 0.99), Some(ms(99)));
        assert_eq!(percentile(&values, 1.0), Some(ms(100)));
        assert_eq!(percentile(&values[..1], 0.99), Some(ms(1)));
        assert_eq!(percentile(&[], 0.5), None);
    }

    #[test]
    fn samples_count_in_the_interval_they_were_due_in() {
        let mut timeline = Timeline::new(Duration::from_secs(60), Duration::from_secs(1));
        // Interval 0: 3 samples due, 2 answered (one late: a failover's resend).
        timeline.add_due(Duration::from_secs(10), 2);
        timeline.add_due(Duration::from_secs(59), 1);
        timeline.add_delivered(Duration::from_secs(10), ms(4));
        timeline.add_delivered(Duration::from_secs(10), ms(31_000));
        // Interval 2 only: interval 1 has nothing due.
        timeline.add_due(Duration::from_secs(125), 1);
        timeline.add_delivered(Duration::from_secs(125), ms(2));
        let rows = timeline.rows();
        assert_eq!(rows.len(), 3);
        assert_eq!((rows[0].start_s, rows[0].end_s), (0.0, 60.0));
        assert_eq!((rows[0].due, rows[0].delivered, rows[0].on_time), (3, 2, 1));
        assert_eq!(rows[0].p50_ms, Some(4.0));
        assert_eq!(rows[0].max_ms, Some(31_000.0));
        assert!((rows[0].delivered_pct() - 200.0 / 3.0).abs() < 1e-12);
        assert!((rows[0].on_time_pct() - 100.0 / 3.0).abs() < 1e-12);
        assert_eq!(
            (rows[1].due, rows[1].delivered, rows[1].p99_ms),
            (0, 0, None)
        );
        assert_eq!(rows[1].delivered_pct(), 100.0);
        assert_eq!(
            (rows[2].start_s, rows[2].due, rows[2].on_time),
            (120.0, 1, 1)
        );
    }
}
