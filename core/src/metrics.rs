//! Detection metrics (SPEC §8): row-level scores on ν = 1 rows, attack events, detection delays and
//! false alarms.
//!
//! Inputs are plain per-row values ([`ScoredRow`]) plus one confirmed alarm c̄ per row, so the same
//! evaluator scores the learned model, the CUSUM comparator and external alarms (Dataset-3's EKF column).
//!
//! Zero denominators follow scikit-learn's `zero_division = 0`: precision, recall, F1, FPR and ADR are 0
//! when their denominator is 0.

use std::collections::HashSet;
use std::ops::Range;

use serde::{Deserialize, Serialize};

/// One evaluated row: where it sits, whether it counts, its ground truth and the detector's score.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoredRow {
    /// Opaque trajectory key; the rows of one trajectory are contiguous and chronological.
    pub trajectory: u64,
    /// Seconds; only differences inside one trajectory are used (delays).
    pub time_s: f64,
    /// ν_t: whether the row enters the row-level metrics.
    pub valid: bool,
    /// Ground truth: `true` = spoofed.
    pub label: bool,
    /// The detector's score before thresholding (p̂_t, or the CUSUM statistic).
    pub score: f64,
}

/// How attack events, detections and delays are defined.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum EventRules {
    /// SPEC §8: an event is a maximal run of label-1 rows inside one trajectory (ν ignored); it is
    /// detected when a confirmed alarm STARTS (0→1) inside it; delay = time_s(onset) − time_s(first row).
    /// An alarm that is on at the first row of a trajectory counts as an onset there (nothing was on
    /// before the trajectory began).
    #[default]
    Spec,
    /// The reference code's legacy evaluator, only to compare with the paper: events
    /// are runs of label-1 ∧ ν = 1 rows (a ν = 0 row splits them); any c̄ = 1 row inside detects, so an
    /// alarm already on at the event start gives delay 0; delays use cumulative positive time steps.
    Legacy,
}

/// Everything SPEC §8 reports for one evaluation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// AUROC of the scores on ν = 1 rows; `None` when a class is absent there.
    pub auroc: Option<f64>,
    /// Average precision of the scores on ν = 1 rows; `None` without positive ν = 1 rows.
    pub auprc: Option<f64>,
    /// TP / (TP + FP), 0 when nothing alarmed.
    pub precision: f64,
    /// TP / (TP + FN), 0 without positives.
    pub recall: f64,
    /// 2TP / (2TP + FP + FN), 0 when that denominator is 0.
    pub f1: f64,
    /// FP / (FP + TN), 0 without negatives.
    pub fpr: f64,
    /// ν = 1 rows with c̄ = 1 and label 1.
    pub true_positives: u64,
    /// ν = 1 rows with c̄ = 1 and label 0.
    pub false_positives: u64,
    /// ν = 1 rows with c̄ = 0 and label 0.
    pub true_negatives: u64,
    /// ν = 1 rows with c̄ = 0 and label 1.
    pub false_negatives: u64,
    /// Number of ν = 1 rows.
    pub valid_rows: u64,
    /// Number of attack events (see [`EventRules`]).
    pub events: u64,
    /// Events with a detection.
    pub detected_events: u64,
    /// Attack detection rate: detected / events, 0 without events.
    pub adr: f64,
    /// Per event, in time order: the detection delay in seconds, `None` when missed.
    pub delays_s: Vec<Option<f64>>,
    /// Mean delay over detected events; `None` when none was detected.
    pub mean_delay_s: Option<f64>,
    /// ν = 1 rows with c̄ = 1 and label 0 (equals `false_positives`).
    pub false_alarm_rows: u64,
    /// Maximal runs of false-alarm rows inside one trajectory.
    pub false_alarm_events: u64,
    /// Confirmed alarms raised on normal rows: onsets (c̄ 0 → 1, or 1 at a trajectory's first row) at
    /// ν = 1, label-0 rows. Unlike `false_alarm_events` it leaves out an alarm that started inside an
    /// attack and outlasts it by a few rows, and one raised within [`EXIT_GRACE_S`] after an attack
    /// (the spoofer's exit), which are not new alarms; the false-alarm budget of the operating-point
    /// search counts these.
    #[serde(default)]
    pub false_alarm_onsets: u64,
}

/// Why rows cannot be evaluated.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MetricsError {
    /// `alarms` must hold exactly one confirmed alarm per row.
    #[error("{alarms} alarms given for {rows} rows; exactly one alarm per row is needed")]
    LengthMismatch {
        /// Number of rows.
        rows: usize,
        /// Number of alarms.
        alarms: usize,
    },
    /// Delays need finite times.
    #[error("row {row}: time_s is not finite ({value})")]
    NonFiniteTime {
        /// 0-based row index.
        row: usize,
        /// The offending time.
        value: f64,
    },
    /// Events and alarm runs are defined per trajectory, so a trajectory must not be split.
    #[error(
        "row {row}: trajectory {trajectory} reappears after another trajectory; the rows of one trajectory must be contiguous"
    )]
    NonContiguousTrajectory {
        /// 0-based index of the row where the trajectory reappears.
        row: usize,
        /// The trajectory key.
        trajectory: u64,
    },
    /// A NaN score has no place in a ranking.
    #[error("row {row}: score is NaN on a valid (ν = 1) row")]
    NanScore {
        /// 0-based row index.
        row: usize,
    },
}

/// Area under the ROC curve (Mann–Whitney U with average ranks for ties), as scikit-learn's
/// `roc_auc_score`. `None` when either class is absent, the lengths differ, or a score is NaN.
pub fn auroc(scores: &[f64], labels: &[bool]) -> Option<f64> {
    if scores.len() != labels.len() || scores.iter().any(|s| s.is_nan()) {
        return None;
    }
    let positives = labels.iter().filter(|&&l| l).count();
    let negatives = labels.len() - positives;
    if positives == 0 || negatives == 0 {
        return None;
    }
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    let mut positive_rank_sum = 0.0;
    for block in tied_blocks(&order, scores) {
        // Ranks are 1-based; tied scores share the average rank of their block.
        let average_rank = (block.start + 1 + block.end) as f64 / 2.0;
        let tied_positives = order[block].iter().filter(|&&i| labels[i]).count();
        positive_rank_sum += average_rank * tied_positives as f64;
    }
    let p = positives as f64;
    Some((positive_rank_sum - p * (p + 1.0) / 2.0) / (p * negatives as f64))
}

/// Average precision, step-wise exactly as scikit-learn's `average_precision_score`:
/// AP = Σ_n (R_n − R_{n−1}) P_n over the distinct score thresholds, highest first (tied scores form one
/// threshold). `None` without positive labels, when the lengths differ, or when a score is NaN.
pub fn average_precision(scores: &[f64], labels: &[bool]) -> Option<f64> {
    if scores.len() != labels.len() || scores.iter().any(|s| s.is_nan()) {
        return None;
    }
    let positives = labels.iter().filter(|&&l| l).count();
    if positives == 0 {
        return None;
    }
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
    let (mut true_pos, mut false_pos) = (0_usize, 0_usize);
    let mut previous_recall = 0.0;
    let mut ap = 0.0;
    for block in tied_blocks(&order, scores) {
        let block_positives = order[block.clone()].iter().filter(|&&i| labels[i]).count();
        true_pos += block_positives;
        false_pos += block.len() - block_positives;
        let precision = true_pos as f64 / (true_pos + false_pos) as f64;
        let recall = true_pos as f64 / positives as f64;
        ap += (recall - previous_recall) * precision;
        previous_recall = recall;
    }
    Some(ap)
}

/// Ranges of `order` (indices sorted by score) whose scores are equal.
fn tied_blocks<'a>(
    order: &'a [usize],
    scores: &'a [f64],
) -> impl Iterator<Item = Range<usize>> + 'a {
    let mut start = 0;
    std::iter::from_fn(move || {
        if start >= order.len() {
            return None;
        }
        let mut end = start + 1;
        while end < order.len() && scores[order[end]] == scores[order[start]] {
            end += 1;
        }
        let block = start..end;
        start = end;
        Some(block)
    })
}

/// Checks what [`evaluate`] needs of the rows: finite times, contiguous trajectories, no NaN score on
/// a valid row. Run once before scoring many alarm sequences on the same rows.
pub fn check_rows(rows: &[ScoredRow]) -> Result<(), MetricsError> {
    let mut finished = HashSet::new();
    for (index, row) in rows.iter().enumerate() {
        if !row.time_s.is_finite() {
            return Err(MetricsError::NonFiniteTime {
                row: index,
                value: row.time_s,
            });
        }
        if row.valid && row.score.is_nan() {
            return Err(MetricsError::NanScore { row: index });
        }
        if index > 0 && rows[index - 1].trajectory != row.trajectory {
            finished.insert(rows[index - 1].trajectory);
            if finished.contains(&row.trajectory) {
                return Err(MetricsError::NonContiguousTrajectory {
                    row: index,
                    trajectory: row.trajectory,
                });
            }
        }
    }
    Ok(())
}

/// Scores confirmed alarms `alarms` (one per row) against the rows: row metrics on ν = 1 rows
/// (AUROC/AUPRC from the scores before thresholding), events, delays and false alarms under `rules`.
///
/// Never fails, for callers that build rows and alarms together: a row without an alarm (`alarms` too
/// short) counts as not alarmed and extra alarms are ignored; every change of trajectory key starts a
/// trajectory; non-finite times give non-finite delays; a NaN score on a valid row makes AUROC/AUPRC
/// `None`. Use [`try_evaluate`] to have such input rejected instead.
pub fn evaluate(rows: &[ScoredRow], alarms: &[bool], rules: EventRules) -> Metrics {
    let padded: Vec<bool>;
    let alarms = if alarms.len() == rows.len() {
        alarms
    } else {
        padded = (0..rows.len())
            .map(|i| alarms.get(i).copied().unwrap_or(false))
            .collect();
        &padded
    };
    let mut metrics = alarm_metrics(rows, alarms, rules);
    let (scores, labels): (Vec<f64>, Vec<bool>) = rows
        .iter()
        .filter(|row| row.valid)
        .map(|row| (row.score, row.label))
        .unzip();
    metrics.auroc = auroc(&scores, &labels);
    metrics.auprc = average_precision(&scores, &labels);
    metrics
}

/// [`evaluate`] after checking the input: one alarm per row and [`check_rows`].
pub fn try_evaluate(
    rows: &[ScoredRow],
    alarms: &[bool],
    rules: EventRules,
) -> Result<Metrics, MetricsError> {
    if rows.len() != alarms.len() {
        return Err(MetricsError::LengthMismatch {
            rows: rows.len(),
            alarms: alarms.len(),
        });
    }
    check_rows(rows)?;
    Ok(evaluate(rows, alarms, rules))
}

/// Attack-free time of the rows in hours: the time steps (t_i − t_{i−1}, inside one trajectory, finite
/// and positive) that end on a label-0 row. The denominator of a false-alarm rate.
pub fn normal_hours(rows: &[ScoredRow]) -> f64 {
    let seconds: f64 = trajectory_ranges(rows)
        .map(|range| {
            rows[range]
                .windows(2)
                .filter(|pair| !pair[1].label)
                .map(|pair| pair[1].time_s - pair[0].time_s)
                .filter(|step| step.is_finite() && *step > 0.0)
                .sum::<f64>()
        })
        .sum();
    seconds / 3600.0
}

/// The trajectories of `rows` grouped by sample rate (Hz, rounded, at least 1, from each
/// trajectory's median sampling interval), with each group's attack-free hours. A false-alarm
/// budget must hold at every rate, not only on average: persistence and noise differ with it.
pub fn rate_groups(rows: &[ScoredRow]) -> Vec<RateGroup> {
    let mut groups: Vec<RateGroup> = Vec::new();
    for range in trajectory_ranges(rows) {
        let Some(rate_hz) = sample_rate_hz(&rows[range.clone()]) else {
            continue;
        };
        let hours = normal_hours(&rows[range.clone()]);
        match groups.iter_mut().find(|g| g.rate_hz == rate_hz) {
            Some(group) => {
                group.trajectories.push(range);
                group.normal_hours += hours;
            }
            None => groups.push(RateGroup {
                rate_hz,
                pace: None,
                trajectories: vec![range],
                normal_hours: hours,
            }),
        }
    }
    groups.sort_by_key(|g| g.rate_hz);
    groups
}

/// [`rate_groups`], then each rate's trajectories again by [`Pace`] from `speeds_mps` (the onboard
/// speed of each row; without one per row, the rate groups alone). A warning budget must hold on
/// open roads as in town: the dead reckoning's error per sample grows with the distance covered,
/// so a point that keeps the budget only on average pages the fleet's fast vehicles.
pub fn rate_and_pace_groups(rows: &[ScoredRow], speeds_mps: &[f64]) -> Vec<RateGroup> {
    let by_rate = rate_groups(rows);
    if speeds_mps.len() != rows.len() {
        return by_rate;
    }
    let mut by_pace = Vec::new();
    for group in &by_rate {
        let (open_road, town): (Vec<_>, Vec<_>) = group
            .trajectories
            .iter()
            .cloned()
            .partition(|range| Pace::of(&speeds_mps[range.clone()]) == Pace::OpenRoad);
        for (pace, trajectories) in [(Pace::Town, town), (Pace::OpenRoad, open_road)] {
            if trajectories.is_empty() {
                continue;
            }
            let hours = trajectories
                .iter()
                .map(|range| normal_hours(&rows[range.clone()]))
                .sum();
            by_pace.push(RateGroup {
                rate_hz: group.rate_hz,
                pace: Some(pace),
                trajectories,
                normal_hours: hours,
            });
        }
    }
    by_rate.into_iter().chain(by_pace).collect()
}

/// A trajectory's sample rate (Hz, rounded, at least 1) from its median sampling interval;
/// `None` for a trajectory without two timed rows.
fn sample_rate_hz(rows: &[ScoredRow]) -> Option<u32> {
    let mut steps: Vec<f64> = rows
        .windows(2)
        .map(|pair| pair[1].time_s - pair[0].time_s)
        .filter(|step| step.is_finite() && *step > 0.0)
        .collect();
    steps.sort_by(f64::total_cmp);
    let median = steps.get(steps.len() / 2)?;
    Some((1.0 / median).round().max(1.0) as u32)
}

/// A trajectory whose median onboard speed while moving reaches this (m/s, 36 km/h) is driven at
/// [`Pace::OpenRoad`]: highways and rural roads, where town traffic, with its stops, turns and
/// queues, rarely keeps that median.
pub const OPEN_ROAD_MEDIAN_SPEED_MPS: f64 = 10.0;
/// Rows slower than this (m/s) are standing or creeping, and left out of a trajectory's pace.
const MOVING_SPEED_MPS: f64 = 1.0;

/// How fast a vehicle drives while it moves, for the false-alarm budget's groups.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Pace {
    /// Median speed while moving below [`OPEN_ROAD_MEDIAN_SPEED_MPS`] (or never moving).
    Town,
    /// Median speed while moving at or above it.
    OpenRoad,
}

impl Pace {
    /// The pace of one trajectory's onboard speeds (m/s; non-finite ones are left out).
    pub fn of(speeds_mps: &[f64]) -> Self {
        let mut moving: Vec<f64> = speeds_mps
            .iter()
            .map(|s| s.abs())
            .filter(|s| s.is_finite() && *s >= MOVING_SPEED_MPS)
            .collect();
        moving.sort_by(f64::total_cmp);
        match moving.get(moving.len() / 2) {
            Some(&median) if median >= OPEN_ROAD_MEDIAN_SPEED_MPS => Self::OpenRoad,
            _ => Self::Town,
        }
    }

    /// How reports and errors name it: "town", "open-road".
    pub fn name(self) -> &'static str {
        match self {
            Self::Town => "town",
            Self::OpenRoad => "open-road",
        }
    }
}

/// The trajectories of one sample rate ([`rate_groups`]), or of one rate and pace
/// ([`rate_and_pace_groups`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RateGroup {
    pub rate_hz: u32,
    /// `None` for every trajectory of the rate.
    pub pace: Option<Pace>,
    /// Row ranges, one per trajectory.
    pub trajectories: Vec<Range<usize>>,
    pub normal_hours: f64,
}

impl RateGroup {
    /// The drives this group holds, for errors: "5 Hz drives", "5 Hz open-road drives".
    pub fn describe(&self) -> String {
        match self.pace {
            None => format!("{} Hz drives", self.rate_hz),
            Some(pace) => format!("{} Hz {} drives", self.rate_hz, pace.name()),
        }
    }

    /// False-alarm onsets of `alarms` in this group's trajectories (as [`Metrics::false_alarm_onsets`]).
    pub fn false_alarm_onsets(&self, rows: &[ScoredRow], alarms: &[bool]) -> u64 {
        self.trajectories
            .iter()
            .map(|range| count_false_alarm_onsets(&rows[range.clone()], &alarms[range.clone()]))
            .sum()
    }
}

/// Every metric except AUROC/AUPRC (which need a sort and do not depend on the alarms).
/// Callers guarantee `rows.len() == alarms.len()`; the operating-point search calls this once per grid
/// point.
pub(crate) fn alarm_metrics(rows: &[ScoredRow], alarms: &[bool], rules: EventRules) -> Metrics {
    let confusion = Confusion::count(rows, alarms);
    let mut delays_s = Vec::new();
    let mut false_alarm_events = 0;
    let mut false_alarm_onsets = 0;
    for trajectory in trajectory_ranges(rows) {
        let rows = &rows[trajectory.clone()];
        let alarms = &alarms[trajectory];
        match rules {
            EventRules::Spec => spec_event_delays(rows, alarms, &mut delays_s),
            EventRules::Legacy => legacy_event_delays(rows, alarms, &mut delays_s),
        }
        false_alarm_events += count_false_alarm_events(rows, alarms);
        false_alarm_onsets += count_false_alarm_onsets(rows, alarms);
    }
    let detected: Vec<f64> = delays_s.iter().flatten().copied().collect();
    let events = delays_s.len() as u64;
    let detected_events = detected.len() as u64;
    let mean_delay_s =
        (!detected.is_empty()).then(|| detected.iter().sum::<f64>() / detected.len() as f64);
    let Confusion { tp, fp, tn, fn_ } = confusion;
    Metrics {
        auroc: None,
        auprc: None,
        precision: ratio(tp, tp + fp),
        recall: ratio(tp, tp + fn_),
        // One division of exact integers, so equal F1 values compare equal in the tie-breaks.
        f1: ratio(2 * tp, 2 * tp + fp + fn_),
        fpr: ratio(fp, fp + tn),
        true_positives: tp,
        false_positives: fp,
        true_negatives: tn,
        false_negatives: fn_,
        valid_rows: tp + fp + tn + fn_,
        events,
        detected_events,
        adr: ratio(detected_events, events),
        delays_s,
        mean_delay_s,
        false_alarm_rows: fp,
        false_alarm_events,
        false_alarm_onsets,
    }
}

/// `numerator / denominator`, 0 when the denominator is 0 (scikit-learn's zero_division = 0).
fn ratio(numerator: u64, denominator: u64) -> f64 {
    if denominator == 0 {
        0.0
    } else {
        numerator as f64 / denominator as f64
    }
}

/// Row-level confusion counts of c̄ against the label on ν = 1 rows.
struct Confusion {
    tp: u64,
    fp: u64,
    tn: u64,
    fn_: u64,
}

impl Confusion {
    fn count(rows: &[ScoredRow], alarms: &[bool]) -> Self {
        let mut counts = Self {
            tp: 0,
            fp: 0,
            tn: 0,
            fn_: 0,
        };
        for (row, &alarm) in rows.iter().zip(alarms).filter(|(row, _)| row.valid) {
            match (alarm, row.label) {
                (true, true) => counts.tp += 1,
                (true, false) => counts.fp += 1,
                (false, false) => counts.tn += 1,
                (false, true) => counts.fn_ += 1,
            }
        }
        counts
    }
}

/// Index ranges of consecutive rows sharing one trajectory key.
pub(crate) fn trajectory_ranges(rows: &[ScoredRow]) -> impl Iterator<Item = Range<usize>> + '_ {
    maximal_runs(rows.len(), |i| Some(rows[i].trajectory))
}

/// Maximal runs of consecutive indices in `0..len` whose key is `Some` and equal.
fn maximal_runs<K: PartialEq>(
    len: usize,
    key: impl Fn(usize) -> Option<K>,
) -> impl Iterator<Item = Range<usize>> {
    let mut start = 0;
    std::iter::from_fn(move || {
        while start < len && key(start).is_none() {
            start += 1;
        }
        if start >= len {
            return None;
        }
        let first_key = key(start);
        let mut end = start + 1;
        while end < len && key(end) == first_key {
            end += 1;
        }
        let run = start..end;
        start = end;
        Some(run)
    })
}

/// Maximal runs of indices where `member` holds.
fn runs_where(len: usize, member: impl Fn(usize) -> bool) -> impl Iterator<Item = Range<usize>> {
    maximal_runs(len, move |i| member(i).then_some(()))
}

/// SPEC §8 events of one trajectory: label-1 runs, detected by the first alarm onset (0→1) inside.
fn spec_event_delays(rows: &[ScoredRow], alarms: &[bool], delays_s: &mut Vec<Option<f64>>) {
    // The trajectory's first row has no predecessor: an alarm on there starts there.
    let is_onset = |i: usize| alarms[i] && (i == 0 || !alarms[i - 1]);
    for event in runs_where(rows.len(), |i| rows[i].label) {
        let onset = event.clone().find(|&i| is_onset(i));
        delays_s.push(onset.map(|i| rows[i].time_s - rows[event.start].time_s));
    }
}

/// Legacy events of one trajectory (the reference code's evaluator): label-1 ∧ ν = 1 runs, detected by any
/// alarm inside, delay in cumulative time (sum of the positive time steps).
fn legacy_event_delays(rows: &[ScoredRow], alarms: &[bool], delays_s: &mut Vec<Option<f64>>) {
    let cumulative_time = cumulative_positive_time(rows);
    for event in runs_where(rows.len(), |i| rows[i].label && rows[i].valid) {
        let first_alarm = event.clone().find(|&i| alarms[i]);
        delays_s.push(first_alarm.map(|i| cumulative_time[i] - cumulative_time[event.start]));
    }
}

/// T(first row) = 0; T(t) = T(t−1) + δ_t when δ_t > 0 (the reference ignores non-positive steps).
fn cumulative_positive_time(rows: &[ScoredRow]) -> Vec<f64> {
    let mut total = 0.0;
    let mut out = Vec::with_capacity(rows.len());
    for (i, row) in rows.iter().enumerate() {
        if i > 0 {
            let step = row.time_s - rows[i - 1].time_s;
            if step > 0.0 {
                total += step;
            }
        }
        out.push(total);
    }
    out
}

/// Maximal runs of false-alarm rows (ν = 1, label 0, c̄ = 1) inside one trajectory.
fn count_false_alarm_events(rows: &[ScoredRow], alarms: &[bool]) -> u64 {
    runs_where(rows.len(), |i| alarms[i] && rows[i].valid && !rows[i].label).count() as u64
}

/// After an attack's last row, the rows of this many seconds are its exit: the spoofer releases
/// the fix, which jumps back to the truth. An alarm raised there is a late reaction to the attack,
/// not a false alarm on attack-free driving; the false-alarm budget leaves it out.
pub const EXIT_GRACE_S: f64 = 30.0;

/// Alarm onsets on ν = 1, label-0 rows inside one trajectory, except within [`EXIT_GRACE_S`] after
/// an attacked row.
fn count_false_alarm_onsets(rows: &[ScoredRow], alarms: &[bool]) -> u64 {
    let mut last_attack_s = f64::NEG_INFINITY;
    let mut onsets = 0;
    for i in 0..rows.len() {
        if rows[i].label {
            last_attack_s = rows[i].time_s;
        }
        let exit = rows[i].time_s - last_attack_s <= EXIT_GRACE_S;
        let onset = alarms[i] && (i == 0 || !alarms[i - 1]);
        if onset && rows[i].valid && !rows[i].label && !exit {
            onsets += 1;
        }
    }
    onsets
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trajectorys_pace_is_its_median_speed_while_moving() {
        // Standing rows do not pull a highway drive into town: moving 9, 11, 12 → median 11.
        assert_eq!(
            Pace::of(&[0.0, 0.0, 0.0, 0.5, 9.0, 11.0, 12.0]),
            Pace::OpenRoad
        );
        // Reversing counts by its magnitude; NaN is left out: moving 9.5, 9.9, 12 → 9.9.
        assert_eq!(Pace::of(&[-9.5, f64::NAN, 9.9, 12.0]), Pace::Town);
        assert_eq!(Pace::of(&[OPEN_ROAD_MEDIAN_SPEED_MPS]), Pace::OpenRoad);
        assert_eq!(Pace::of(&[0.0, 0.2]), Pace::Town);
        assert_eq!(Pace::of(&[]), Pace::Town);
    }

    #[test]
    fn false_alarm_onsets_leave_out_an_alarm_that_outlasts_its_attack() {
        let row = |label| ScoredRow {
            trajectory: 0,
            time_s: 0.0,
            valid: true,
            label,
            score: 0.0,
        };
        // Attack rows 1–2; the alarm starts inside it and runs two rows past it (one FA event, no
        // new alarm), then a separate alarm starts on normal row 6 (one event, one onset).
        let rows = [false, true, true, false, false, false, false, false].map(row);
        let alarms = [false, false, true, true, true, false, true, true];
        let m = alarm_metrics(&rows, &alarms, EventRules::Spec);
        assert_eq!((m.false_alarm_rows, m.false_alarm_events), (4, 2));
        // All at t = 0 here, so the second alarm is inside the exit grace too.
        assert_eq!(m.false_alarm_onsets, 0);
        // The same at 20 s per row: row 6 is 80 s after the attack's last row (row 2).
        let spaced: Vec<ScoredRow> = rows
            .iter()
            .enumerate()
            .map(|(i, r)| ScoredRow {
                time_s: 20.0 * i as f64,
                ..*r
            })
            .collect();
        assert_eq!(
            alarm_metrics(&spaced, &alarms, EventRules::Spec).false_alarm_onsets,
            1
        );
        // At 5 s per row it is 20 s after: the spoofer's exit, not a false alarm.
        let close: Vec<ScoredRow> = rows
            .iter()
            .enumerate()
            .map(|(i, r)| ScoredRow {
                time_s: 5.0 * i as f64,
                ..*r
            })
            .collect();
        assert_eq!(
            alarm_metrics(&close, &alarms, EventRules::Spec).false_alarm_onsets,
            0
        );
    }

    #[test]
    fn normal_hours_count_steps_that_end_on_normal_rows_inside_trajectories() {
        let row = |trajectory, time_s, label| ScoredRow {
            trajectory,
            time_s,
            valid: true,
            label,
            score: 0.0,
        };
        let rows = [
            row(0, 0.0, false),
            row(0, 10.0, false),   // +10
            row(0, 20.0, true),    // spoofed: not counted
            row(0, 3600.0, false), // +3580
            row(1, 9000.0, false), // new trajectory: the gap is not counted
            row(1, 9001.0, false), // +1
            row(1, 9001.0, false), // zero step
        ];
        assert_eq!(normal_hours(&rows), 3591.0 / 3600.0);
        assert_eq!(normal_hours(&[]), 0.0);
    }

    /// One trajectory (key 0) at 1 Hz from t = 100 s, all rows valid, score 0.
    fn rows_from_labels(labels: &[u8]) -> Vec<ScoredRow> {
        labels
            .iter()
            .enumerate()
            .map(|(i, &label)| ScoredRow {
                trajectory: 0,
                time_s: 100.0 + i as f64,
                valid: true,
                label: label == 1,
                score: 0.0,
            })
            .collect()
    }

    fn bits(values: &[u8]) -> Vec<bool> {
        values.iter().map(|&v| v == 1).collect()
    }

    #[test]
    fn auroc_matches_hand_computed_values() {
        // Perfect ranking, reversed ranking, and sklearn's documented example (0.75).
        assert_eq!(
            auroc(&[0.1, 0.2, 0.8, 0.9], &[false, false, true, true]),
            Some(1.0)
        );
        assert_eq!(
            auroc(&[0.9, 0.8, 0.2, 0.1], &[false, false, true, true]),
            Some(0.0)
        );
        assert_eq!(
            auroc(&[0.1, 0.4, 0.35, 0.8], &[false, false, true, true]),
            Some(0.75)
        );
        // All tied: 0.5.
        assert_eq!(auroc(&[0.5; 4], &[false, true, false, true]), Some(0.5));
        assert_eq!(auroc(&[0.5, 0.6], &[true, true]), None);
    }

    #[test]
    fn auroc_rejects_bad_input_without_panicking() {
        assert_eq!(auroc(&[0.1, 0.2], &[true]), None);
        assert_eq!(auroc(&[0.1, f64::NAN], &[true, false]), None);
    }

    #[test]
    fn average_precision_matches_sklearn_examples() {
        // sklearn docs: average_precision_score([0, 0, 1, 1], [0.1, 0.4, 0.35, 0.8]) = 0.8333...
        let ap = average_precision(&[0.1, 0.4, 0.35, 0.8], &[false, false, true, true])
            .expect("positives exist");
        assert!((ap - 5.0 / 6.0).abs() < 1e-15, "{ap}");
        // Perfect ranking → 1; all positives → 1.
        assert_eq!(average_precision(&[0.1, 0.9], &[false, true]), Some(1.0));
        assert_eq!(average_precision(&[0.3, 0.2], &[true, true]), Some(1.0));
        // Reversed ranking of 1 positive among 4: the positive is found last, P = 1/4.
        assert_eq!(
            average_precision(&[0.4, 0.3, 0.2, 0.1], &[false, false, false, true]),
            Some(0.25)
        );
    }

    #[test]
    fn average_precision_treats_tied_scores_as_one_threshold() {
        // All tied: one threshold with P = 2/4 at R = 1 → AP = 0.5 (sklearn gives 0.5).
        assert_eq!(
            average_precision(&[0.5; 4], &[true, false, true, false]),
            Some(0.5)
        );
        // Scores [0.9, 0.5, 0.5, 0.1], labels [1, 1, 0, 1]: thresholds 0.9 (P 1, R 1/3),
        // 0.5 (P 2/3, R 2/3), 0.1 (P 3/4, R 1) → 1/3 + 1/3·2/3 + 1/3·3/4 = 0.8055...
        let ap = average_precision(&[0.9, 0.5, 0.5, 0.1], &[true, true, false, true])
            .expect("positives exist");
        assert!(
            (ap - (1.0 / 3.0 + 2.0 / 9.0 + 1.0 / 4.0)).abs() < 1e-15,
            "{ap}"
        );
    }

    #[test]
    fn average_precision_is_none_without_positives_or_with_bad_input() {
        assert_eq!(average_precision(&[0.1, 0.2], &[false, false]), None);
        assert_eq!(average_precision(&[0.1, 0.2], &[true]), None);
        assert_eq!(average_precision(&[0.1, f64::NAN], &[true, false]), None);
        assert_eq!(average_precision(&[], &[]), None);
    }

    #[test]
    fn confusion_precision_recall_f1_fpr_on_valid_rows_only() {
        let mut rows = rows_from_labels(&[1, 1, 1, 0, 0, 0, 0, 1]);
        // The last row is invalid: its alarm and label do not count.
        rows[7].valid = false;
        let alarms = bits(&[1, 1, 0, 1, 0, 0, 0, 1]);
        let m = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(
            (
                m.true_positives,
                m.false_positives,
                m.true_negatives,
                m.false_negatives
            ),
            (2, 1, 3, 1)
        );
        assert_eq!(m.valid_rows, 7);
        assert_eq!(m.precision, 2.0 / 3.0);
        assert_eq!(m.recall, 2.0 / 3.0);
        assert_eq!(m.f1, 4.0 / 6.0);
        assert_eq!(m.fpr, 0.25);
        assert_eq!(m.false_alarm_rows, 1);
    }

    #[test]
    fn zero_denominators_give_zero() {
        // No alarms and no positives.
        let rows = rows_from_labels(&[0, 0, 0]);
        let m = try_evaluate(&rows, &[false; 3], EventRules::Spec).expect("valid input");
        assert_eq!(
            (m.precision, m.recall, m.f1, m.fpr, m.adr),
            (0.0, 0.0, 0.0, 0.0, 0.0)
        );
        assert_eq!(
            (m.events, m.mean_delay_s, m.auroc, m.auprc),
            (0, None, None, None)
        );
        // No valid rows at all.
        let mut rows = rows_from_labels(&[1, 0]);
        rows.iter_mut().for_each(|r| r.valid = false);
        let m = try_evaluate(&rows, &[true, true], EventRules::Spec).expect("valid input");
        assert_eq!(
            (m.valid_rows, m.precision, m.recall, m.f1, m.fpr),
            (0, 0.0, 0.0, 0.0, 0.0)
        );
    }

    #[test]
    fn auroc_and_auprc_use_scores_of_valid_rows() {
        let mut rows = rows_from_labels(&[0, 0, 1, 1, 1]);
        for (row, score) in rows.iter_mut().zip([0.1, 0.4, 0.35, 0.8, 0.0]) {
            row.score = score;
        }
        // The badly ranked last row is invalid and must not count.
        rows[4].valid = false;
        let m = try_evaluate(&rows, &[false; 5], EventRules::Spec).expect("valid input");
        assert_eq!(m.auroc, Some(0.75));
        let auprc = m.auprc.expect("positives exist");
        assert!((auprc - 5.0 / 6.0).abs() < 1e-15);
    }

    #[test]
    fn spec_events_need_an_alarm_onset_inside_and_measure_delay_from_the_first_row() {
        // Events: rows 2..6 and 9..11. Alarm 1 starts at row 4 (delay 2 s); alarm 2 is already on
        // when event 2 starts (rows 8..12) and never restarts inside it → missed.
        let rows = rows_from_labels(&[0, 0, 1, 1, 1, 1, 0, 0, 0, 1, 1, 0]);
        let alarms = bits(&[0, 0, 0, 0, 1, 1, 1, 0, 1, 1, 1, 1]);
        let m = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(m.delays_s, vec![Some(2.0), None]);
        assert_eq!((m.events, m.detected_events, m.adr), (2, 1, 0.5));
        assert_eq!(m.mean_delay_s, Some(2.0));
        // False-alarm rows: 6, 8, 11 → events {6}, {8}, {11}.
        assert_eq!((m.false_alarm_rows, m.false_alarm_events), (3, 3));
    }

    #[test]
    fn spec_delay_uses_time_differences_not_row_counts() {
        let mut rows = rows_from_labels(&[0, 1, 1, 1]);
        rows[2].time_s += 1.0; // a 2 s step
        rows[3].time_s += 1.0;
        let m = try_evaluate(&rows, &bits(&[0, 0, 0, 1]), EventRules::Spec).expect("valid input");
        assert_eq!(m.delays_s, vec![Some(3.0)]);
    }

    #[test]
    fn spec_counts_an_alarm_on_at_a_trajectory_start_as_an_onset() {
        // Two trajectories; the alarm is on through the boundary. In trajectory 1 the event starts at its
        // first row where the alarm is on: nothing was on before the trajectory, so that is an onset.
        let mut rows = rows_from_labels(&[0, 0, 1, 1]);
        rows[2].trajectory = 1;
        rows[3].trajectory = 1;
        let m = try_evaluate(&rows, &bits(&[0, 1, 1, 1]), EventRules::Spec).expect("valid input");
        assert_eq!(m.delays_s, vec![Some(0.0)]);
        assert_eq!(m.false_alarm_events, 1);
    }

    #[test]
    fn events_and_false_alarm_runs_stop_at_trajectory_boundaries() {
        // Label-1 run spans two trajectories → two events; false alarms likewise → two events.
        let mut rows = rows_from_labels(&[1, 1, 1, 1, 0, 0, 0, 0]);
        for row in &mut rows[2..6] {
            row.trajectory = 7;
        }
        for row in &mut rows[6..] {
            row.trajectory = 9;
        }
        let alarms = bits(&[0, 1, 0, 0, 0, 1, 1, 0]);
        let m = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(m.delays_s, vec![Some(1.0), None]);
        assert_eq!((m.false_alarm_rows, m.false_alarm_events), (2, 2));
    }

    #[test]
    fn spec_events_ignore_validity_but_false_alarm_events_are_split_by_invalid_rows() {
        // Row 2 invalid inside an attack: Spec keeps one event; the alarm restarting at row 3 after the
        // invalid row is the first onset inside the event.
        let mut rows = rows_from_labels(&[0, 1, 1, 1, 0, 0, 0]);
        rows[2].valid = false;
        rows[5].valid = false;
        let alarms = bits(&[0, 0, 0, 1, 1, 1, 1]);
        let spec = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(spec.delays_s, vec![Some(2.0)]);
        // False-alarm rows 4 and 6 (row 5 is invalid) → two runs.
        assert_eq!((spec.false_alarm_rows, spec.false_alarm_events), (2, 2));
        // Legacy: the invalid row splits the attack into {1} (missed) and {3} (delay 0).
        let legacy = try_evaluate(&rows, &alarms, EventRules::Legacy).expect("valid input");
        assert_eq!(legacy.delays_s, vec![None, Some(0.0)]);
        assert_eq!((legacy.adr, legacy.mean_delay_s), (0.5, Some(0.0)));
        assert_eq!(legacy.false_alarm_events, 2);
    }

    #[test]
    fn legacy_credits_an_alarm_already_on_with_zero_delay() {
        let rows = rows_from_labels(&[0, 0, 1, 1, 1]);
        let alarms = bits(&[0, 1, 1, 1, 1]);
        let spec = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(spec.delays_s, vec![None]);
        let legacy = try_evaluate(&rows, &alarms, EventRules::Legacy).expect("valid input");
        assert_eq!(legacy.delays_s, vec![Some(0.0)]);
        assert_eq!(legacy.adr, 1.0);
    }

    #[test]
    fn legacy_delay_is_cumulative_positive_time() {
        // Times 0, 1, 1 (zero step), 0.8 (backward step, ignored), 3.8: T = 0, 1, 1, 1, 4.
        let mut rows = rows_from_labels(&[1, 1, 1, 1, 1]);
        for (row, t) in rows.iter_mut().zip([0.0, 1.0, 1.0, 0.8, 3.8]) {
            row.time_s = t;
        }
        let alarms = bits(&[0, 0, 0, 0, 1]);
        let legacy = try_evaluate(&rows, &alarms, EventRules::Legacy).expect("valid input");
        assert_eq!(legacy.delays_s, vec![Some(4.0)]);
        let spec = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(spec.delays_s, vec![Some(3.8)]);
    }

    #[test]
    fn mean_delay_averages_detected_events_only() {
        let rows = rows_from_labels(&[1, 1, 1, 0, 1, 1, 0, 1, 1, 1, 1]);
        let alarms = bits(&[0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 1]);
        let m = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(m.delays_s, vec![Some(1.0), None, Some(3.0)]);
        assert_eq!(m.mean_delay_s, Some(2.0));
        assert_eq!(m.adr, 2.0 / 3.0);
    }

    #[test]
    fn evaluate_rejects_bad_input_with_precise_errors() {
        let rows = rows_from_labels(&[0, 1, 0]);
        assert_eq!(
            try_evaluate(&rows, &[false; 2], EventRules::Spec),
            Err(MetricsError::LengthMismatch { rows: 3, alarms: 2 })
        );
        let mut bad_time = rows.clone();
        bad_time[1].time_s = f64::NAN;
        assert!(matches!(
            try_evaluate(&bad_time, &[false; 3], EventRules::Spec),
            Err(MetricsError::NonFiniteTime { row: 1, .. })
        ));
        let mut split = rows.clone();
        split[1].trajectory = 5;
        assert_eq!(
            try_evaluate(&split, &[false; 3], EventRules::Spec),
            Err(MetricsError::NonContiguousTrajectory {
                row: 2,
                trajectory: 0
            })
        );
        let mut nan_score = rows.clone();
        nan_score[2].score = f64::NAN;
        assert_eq!(
            try_evaluate(&nan_score, &[false; 3], EventRules::Spec),
            Err(MetricsError::NanScore { row: 2 })
        );
        // A NaN score on an invalid row is fine: it never enters the ranking.
        nan_score[2].valid = false;
        assert!(try_evaluate(&nan_score, &[false; 3], EventRules::Spec).is_ok());
    }

    #[test]
    fn lenient_evaluate_never_panics_and_agrees_on_good_input() {
        let rows = rows_from_labels(&[0, 1, 1, 0]);
        let alarms = bits(&[0, 0, 1, 1]);
        let strict = try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid input");
        assert_eq!(evaluate(&rows, &alarms, EventRules::Spec), strict);
        // Too few alarms: the missing ones count as off (same as passing them as false).
        let short = evaluate(&rows, &alarms[..3], EventRules::Spec);
        assert_eq!(
            short,
            evaluate(&rows, &bits(&[0, 0, 1, 0]), EventRules::Spec)
        );
        // Too many alarms: the extra ones are ignored.
        let long = evaluate(&rows, &bits(&[0, 0, 1, 1, 1]), EventRules::Spec);
        assert_eq!(long, strict);
        // A NaN score on a valid row: no ranking metrics, the rest unchanged.
        let mut nan_rows = rows.clone();
        nan_rows[0].score = f64::NAN;
        let m = evaluate(&nan_rows, &alarms, EventRules::Spec);
        assert_eq!((m.auroc, m.auprc, m.f1), (None, None, strict.f1));
    }

    #[test]
    fn metrics_round_trip_through_json() {
        let rows = rows_from_labels(&[0, 1, 1]);
        let m = try_evaluate(&rows, &bits(&[0, 0, 1]), EventRules::Spec).expect("valid input");
        let json = serde_json::to_string(&m).expect("serialisable");
        let back: Metrics = serde_json::from_str(&json).expect("deserialisable");
        assert_eq!(back, m);
    }
}
