//! Vehicle ids: 1 to [`MAX_VEHICLE_ID_LEN`] characters of `[A-Za-z0-9._:-]`, written once as the
//! [`VehicleId`] newtype (for the server's validation) and [`is_vehicle_id_char`] (for clients that
//! turn recorded ids into acceptable ones).
//!
//! Owns the rule and the wording of its violations only; it must not know about gRPC statuses,
//! field paths or sessions (the server's edge maps a [`VehicleIdError`] to a field violation).

use std::fmt;

use super::limits::MAX_VEHICLE_ID_LEN;

/// Why a string is not a vehicle id. The messages are the field violations the server reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum VehicleIdError {
    /// Nothing was given.
    #[error("required")]
    Empty,
    /// Longer than [`MAX_VEHICLE_ID_LEN`] bytes (which is characters, for a valid id).
    #[error("at most {MAX_VEHICLE_ID_LEN} characters")]
    TooLong,
    /// A character outside `[A-Za-z0-9._:-]`.
    #[error("only letters, digits and . _ : - are allowed")]
    Malformed,
}

/// Whether `c` may appear in a vehicle id: an ASCII letter or digit, `.`, `_`, `:` or `-`.
pub fn is_vehicle_id_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | ':' | '-')
}

/// A checked vehicle id.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VehicleId(String);

impl VehicleId {
    /// Checks `id`: empty first, then its length, then its characters (the first failing check
    /// is the one reported).
    pub fn parse(id: &str) -> Result<Self, VehicleIdError> {
        if id.is_empty() {
            return Err(VehicleIdError::Empty);
        }
        if id.len() > MAX_VEHICLE_ID_LEN {
            return Err(VehicleIdError::TooLong);
        }
        if !id.chars().all(is_vehicle_id_char) {
            return Err(VehicleIdError::Malformed);
        }
        Ok(Self(id.to_string()))
    }

    /// The id as text.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// The id as an owned string.
    pub fn into_string(self) -> String {
        self.0
    }
}

impl fmt::Display for VehicleId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_valid_id_is_kept_as_given() {
        let id = VehicleId::parse("truck-7.a:b_c").expect("valid");
        assert_eq!(id.as_str(), "truck-7.a:b_c");
        assert_eq!(id.to_string(), "truck-7.a:b_c");
        assert_eq!(id.into_string(), "truck-7.a:b_c");
        let longest = "x".repeat(MAX_VEHICLE_ID_LEN);
        assert_eq!(
            VehicleId::parse(&longest).map(VehicleId::into_string),
            Ok(longest)
        );
    }

    #[test]
    fn each_violation_has_its_message() {
        assert_eq!(VehicleId::parse(""), Err(VehicleIdError::Empty));
        assert_eq!(
            VehicleId::parse(&"x".repeat(MAX_VEHICLE_ID_LEN + 1)),
            Err(VehicleIdError::TooLong)
        );
        assert_eq!(
            VehicleId::parse("has space"),
            Err(VehicleIdError::Malformed)
        );
        assert_eq!(VehicleIdError::Empty.to_string(), "required");
        assert_eq!(
            VehicleIdError::TooLong.to_string(),
            "at most 128 characters"
        );
        assert_eq!(
            VehicleIdError::Malformed.to_string(),
            "only letters, digits and . _ : - are allowed"
        );
    }

    #[test]
    fn length_is_checked_before_characters_and_counts_bytes() {
        // 65 two-byte characters: 130 bytes, so too long rather than malformed.
        assert_eq!(
            VehicleId::parse(&"é".repeat(65)),
            Err(VehicleIdError::TooLong)
        );
        assert_eq!(
            VehicleId::parse(&"é".repeat(64)),
            Err(VehicleIdError::Malformed)
        );
    }

    #[test]
    fn the_character_rule_allows_exactly_the_documented_set() {
        for c in ['a', 'Z', '0', '9', '.', '_', ':', '-'] {
            assert!(is_vehicle_id_char(c), "{c:?}");
        }
        for c in [' ', '/', '#', 'é', '\0', '+'] {
            assert!(!is_vehicle_id_char(c), "{c:?}");
        }
    }
}
