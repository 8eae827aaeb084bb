//! Resource names: `models/{id}`, `datasets/{id}` and `operations/{id}` as small newtypes, so no
//! code formats or strips these prefixes by hand.
//!
//! Parsing accepts the full name or a bare id (both forms have always been accepted on the wire);
//! an id is 1 to [`MAX_RESOURCE_ID_LEN`] characters of `[A-Za-z0-9._-]`.

use std::fmt;

use super::limits::MAX_RESOURCE_ID_LEN;

/// Why a string is not a resource name of the expected collection.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    /// Nothing was given.
    #[error("required")]
    Empty,
    /// The id is longer than [`MAX_RESOURCE_ID_LEN`].
    #[error("the id is longer than {MAX_RESOURCE_ID_LEN} characters")]
    TooLong,
    /// The id holds a character outside `[A-Za-z0-9._-]` (e.g. a `/` of another collection).
    #[error("expected {collection}/{{id}} with an id of letters, digits, '.', '_' or '-'")]
    Malformed {
        /// The collection that was expected, e.g. `models`.
        collection: &'static str,
    },
}

/// Splits `name` (`{collection}/{id}` or a bare id) and checks the id.
fn parse_id(collection: &'static str, name: &str) -> Result<String, NameError> {
    let id = name
        .strip_prefix(collection)
        .and_then(|rest| rest.strip_prefix('/'))
        .unwrap_or(name);
    if id.is_empty() {
        return Err(NameError::Empty);
    }
    if id.len() > MAX_RESOURCE_ID_LEN {
        return Err(NameError::TooLong);
    }
    if !id
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
    {
        return Err(NameError::Malformed { collection });
    }
    Ok(id.to_string())
}

macro_rules! resource_name {
    ($(#[$doc:meta])* $name:ident, $collection:literal) => {
        $(#[$doc])*
        #[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
        pub struct $name(String);

        impl $name {
            /// The collection segment of the name.
            pub const COLLECTION: &'static str = $collection;

            /// The name of the resource with this id (ids are chosen by the server, so trusted).
            pub fn from_id(id: impl Into<String>) -> Self {
                Self(id.into())
            }

            /// Parses `{collection}/{id}` or a bare `{id}`.
            pub fn parse(name: &str) -> Result<Self, NameError> {
                parse_id(Self::COLLECTION, name).map(Self)
            }

            /// The id without the collection.
            pub fn id(&self) -> &str {
                &self.0
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, "{}/{}", Self::COLLECTION, self.0)
            }
        }
    };
}

resource_name!(
    /// `models/{id}`: a model in the registry.
    ModelName,
    "models"
);
resource_name!(
    /// `datasets/{id}`: a stored dataset.
    DatasetName,
    "datasets"
);
resource_name!(
    /// `operations/{id}`: a training or evaluation job.
    OperationName,
    "operations"
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_accept_the_full_form_and_a_bare_id() {
        let full = ModelName::parse("models/abc").expect("full name");
        assert_eq!(full.id(), "abc");
        assert_eq!(full, ModelName::parse("abc").expect("bare id"));
        assert_eq!(full.to_string(), "models/abc");
        assert_eq!(OperationName::from_id("x1").to_string(), "operations/x1");
    }

    #[test]
    fn bad_names_say_why() {
        assert_eq!(DatasetName::parse(""), Err(NameError::Empty));
        assert_eq!(DatasetName::parse("datasets/"), Err(NameError::Empty));
        assert_eq!(
            DatasetName::parse("models/abc"),
            Err(NameError::Malformed {
                collection: "datasets"
            })
        );
        assert_eq!(
            ModelName::parse(&"x".repeat(MAX_RESOURCE_ID_LEN + 1)),
            Err(NameError::TooLong)
        );
    }
}
