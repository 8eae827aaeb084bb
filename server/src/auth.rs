//! Bearer-token authentication of the API services: `authorization: Bearer <token>` when a token is
//! configured, checked by an interceptor in front of every API service.
//!
//! It owns the check and nothing else: which services it guards is the router's choice
//! (`crate::router`), and the token comes from the configuration.

use std::sync::Arc;

use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Status};

use crate::telemetry;

/// Checks `authorization: Bearer <token>` when a token is configured: the scheme in any case, the
/// token in constant time. Ours rather than tower-http's `ValidateRequestHeaderLayer::bearer`,
/// which matches the header with `==` (case-sensitive scheme, time depending on the token).
///
/// Health and reflection stay open on purpose: health is for load balancers and orchestrators that
/// hold no token, and reflection serves only the public schema (the `.proto` files of this
/// repository), no data. Whoever must not even reach them is kept out by mutual TLS.
#[derive(Clone)]
pub struct BearerAuth {
    expected: Option<Arc<str>>,
}

impl BearerAuth {
    /// Requires `token` on every guarded call; `None` lets every call through.
    pub fn new(token: Option<&str>) -> Self {
        Self {
            expected: token.map(Arc::from),
        }
    }

    /// `service` behind this check (every API service is; health and reflection are not).
    pub fn guard<S>(&self, service: S) -> InterceptedService<S, BearerAuth> {
        InterceptedService::new(service, self.clone())
    }
}

impl Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        let presented = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(bearer_token);
        match presented {
            Some(token) if tokens_match(token, expected) => Ok(request),
            _ => {
                telemetry::unauthenticated();
                Err(Status::unauthenticated("missing or wrong bearer token"))
            }
        }
    }
}

/// The token of an `authorization` value `Bearer <token>` (the scheme is case-insensitive, RFC
/// 9110 §11.1); `None` for another scheme or an empty token.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim().split_once(' ')?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// Compares in time independent of where the tokens differ (their length is not secret).
fn tokens_match(presented: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    bool::from(presented.as_bytes().ct_eq(expected.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bearer_scheme_is_case_insensitive_and_an_empty_token_is_none() {
        assert_eq!(bearer_token("Bearer abc"), Some("abc"));
        assert_eq!(bearer_token("bearer abc"), Some("abc"));
        assert_eq!(bearer_token("BEARER   abc "), Some("abc"));
        assert_eq!(bearer_token("Bearer "), None);
        assert_eq!(bearer_token("Bearer"), None);
        assert_eq!(bearer_token("Basic abc"), None);
        assert!(tokens_match("abc", "abc"));
        assert!(!tokens_match("abd", "abc"));
        assert!(!tokens_match("", "abc"));
        assert!(!tokens_match("abcd", "abc"));
    }
}
