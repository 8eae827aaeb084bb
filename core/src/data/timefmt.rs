//! The AV-GPS time formats: `H:MM:SS` durations (hours may exceed 24),
//! `H:MM:SS` 24-hour clock times and month-first `M/D/YYYY` dates. Empty text is `None`.
//!
//! Owns timestamp parsing. Must not know about file formats.

/// Seconds of an `H:MM:SS[.fff]` duration.
pub fn parse_duration(text: &str) -> Result<Option<f64>, String> {
    parse_hms(text, None, "a duration H:MM:SS")
}

/// Seconds since midnight of an `H:MM:SS[.fff]` 24-hour clock time.
pub fn parse_clock_time(text: &str) -> Result<Option<f64>, String> {
    parse_hms(text, Some(23), "a 24-hour time H:MM:SS")
}

/// Days since 1970-01-01 of a month-first `M/D/YYYY` date.
pub fn parse_date(text: &str) -> Result<Option<i64>, String> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(None);
    }
    let bad = || format!("expected a date M/D/YYYY, got \"{text}\"");
    let [m, d, y] = three_parts(text, '/').ok_or_else(bad)?;
    let (Some(month), Some(day), Some(year)) = (digits(m, 2), digits(d, 2), digits(y, 4)) else {
        return Err(bad());
    };
    if y.len() != 4 || !(1..=12).contains(&month) || day < 1 || day > days_in_month(year, month) {
        return Err(bad());
    }
    Ok(Some(days_from_civil(year as i64, month, day)))
}

/// The three `sep`-separated fields of `text`, or `None` when there are more or fewer.
fn three_parts(text: &str, sep: char) -> Option<[&str; 3]> {
    let mut parts = text.split(sep);
    match (parts.next(), parts.next(), parts.next(), parts.next()) {
        (Some(a), Some(b), Some(c), None) => Some([a, b, c]),
        _ => None,
    }
}

fn parse_hms(text: &str, max_hour: Option<u64>, what: &str) -> Result<Option<f64>, String> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(None);
    }
    let bad = || format!("expected {what}, got \"{text}\"");
    let [h, m, s] = three_parts(text, ':').ok_or_else(bad)?;
    let (Some(hours), Some(minutes)) = (digits(h, 9), digits(m, 2)) else {
        return Err(bad());
    };
    let seconds = parse_seconds(s).ok_or_else(bad)?;
    if minutes > 59 || seconds >= 60.0 || max_hour.is_some_and(|max| hours > max) {
        return Err(bad());
    }
    Ok(Some(
        hours as f64 * 3600.0 + minutes as f64 * 60.0 + seconds,
    ))
}

/// 1 to `max_len` ASCII digits.
fn digits(text: &str, max_len: usize) -> Option<u64> {
    let ok = !text.is_empty() && text.len() <= max_len && text.bytes().all(|b| b.is_ascii_digit());
    if ok { text.parse().ok() } else { None }
}

/// `SS` or `SS.fff`: two-digit whole seconds with an optional fraction.
fn parse_seconds(text: &str) -> Option<f64> {
    let (whole, fraction) = text.split_once('.').unwrap_or((text, ""));
    let fraction_ok = fraction.bytes().all(|b| b.is_ascii_digit());
    if digits(whole, 2).is_none() || !fraction_ok || (text.contains('.') && fraction.is_empty()) {
        return None;
    }
    text.parse().ok()
}

fn is_leap(year: u64) -> bool {
    (year.is_multiple_of(4) && !year.is_multiple_of(100)) || year.is_multiple_of(400)
}

fn days_in_month(year: u64, month: u64) -> u64 {
    match month {
        2 if is_leap(year) => 29,
        2 => 28,
        4 | 6 | 9 | 11 => 30,
        _ => 31,
    }
}

/// Days since 1970-01-01 (Howard Hinnant's `days_from_civil`).
fn days_from_civil(year: i64, month: u64, day: u64) -> i64 {
    let (month, day) = (month as i64, day as i64);
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_may_exceed_a_day() {
        assert_eq!(parse_duration("0:02:32"), Ok(Some(152.0)));
        assert_eq!(parse_duration("15:03:55"), Ok(Some(54_235.0)));
        assert_eq!(parse_duration("100:00:01.5"), Ok(Some(360_001.5)));
        assert_eq!(parse_duration(" "), Ok(None));
        for bad in [
            "1:2",
            "0:60:00",
            "0:00:60",
            "a:00:00",
            "0:00:01.",
            "-1:00:00",
            "0:00:00:00",
        ] {
            assert!(parse_duration(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn clock_times_are_24_hour() {
        assert_eq!(parse_clock_time("10:55:59"), Ok(Some(39_359.0)));
        assert_eq!(parse_clock_time("23:59:59"), Ok(Some(86_399.0)));
        assert!(parse_clock_time("24:00:00").is_err());
        assert!(parse_clock_time("10:55").is_err());
    }

    #[test]
    fn dates_are_month_first() {
        // 2022-05-24 is day 19,136 since the epoch; 5/21 three days earlier.
        assert_eq!(parse_date("5/24/2022"), Ok(Some(19_136)));
        assert_eq!(parse_date("05/21/2022"), Ok(Some(19_133)));
        assert_eq!(parse_date("1/1/1970"), Ok(Some(0)));
        assert_eq!(parse_date("2/29/2024"), Ok(Some(19_782)));
        assert_eq!(parse_date(""), Ok(None));
        for bad in [
            "24/5/2022",
            "2/29/2023",
            "5/24/22",
            "5-24-2022",
            "5/24/2022/1",
            "5//2022",
        ] {
            assert!(parse_date(bad).is_err(), "{bad}");
        }
    }
}
