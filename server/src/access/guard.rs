//! The guard in front of every API service: identifies each call's caller, refuses the call when
//! its role may not make it, and hands the [`Caller`] to the service in the request's extensions.
//! It owns identification (bearer tokens in constant time, client certificates by name and
//! fingerprint) and nothing else.
//!
//! Health and reflection stay unguarded on purpose: health is for load balancers and orchestrators
//! that hold no credential, and reflection serves only the public schema, no data. Whoever must
//! not even reach them is kept out by mutual TLS.

use std::convert::Infallible;
use std::sync::Arc;
use std::task::{Context, Poll};

use tokio_util::either::Either;
use tonic::body::Body;
use tonic::server::NamedService;
use tonic::transport::server::{TcpConnectInfo, TlsConnectInfo};
use tonic::{Code, Status};
use tower_service::Service;

use super::policy::need_of;
use super::{Access, Caller, Grant, Identities, denied};
use crate::identity::sha256_hex;
use crate::telemetry;

/// `inner` behind the guard of `access`.
#[derive(Clone)]
pub struct Guarded<S> {
    inner: S,
    access: Arc<Access>,
}

impl<S> Guarded<S> {
    pub fn new(inner: S, access: Arc<Access>) -> Self {
        Guarded { inner, access }
    }
}

impl<S: NamedService> NamedService for Guarded<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B> Service<http::Request<B>> for Guarded<S>
where
    S: Service<http::Request<B>, Response = http::Response<Body>, Error = Infallible>,
{
    type Response = http::Response<Body>;
    type Error = Infallible;
    type Future = Either<S::Future, std::future::Ready<Result<http::Response<Body>, Infallible>>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: http::Request<B>) -> Self::Future {
        let (method, need) = need_of(request.uri().path());
        let identities = self.access.current();
        let certificate = request
            .extensions()
            .get::<TlsConnectInfo<TcpConnectInfo>>()
            .and_then(TlsConnectInfo::peer_certs);
        let identified = identify(
            &identities,
            request
                .headers()
                .get("authorization")
                .and_then(|v| v.to_str().ok()),
            certificate
                .as_ref()
                .and_then(|chain| chain.first())
                .map(|c| c.as_ref()),
        );
        let outcome = identified.and_then(|grant| {
            if need.allows(grant.role) {
                Ok(grant)
            } else {
                Err(denied(
                    &grant,
                    method,
                    &format!("{method} (it needs {need:?})"),
                ))
            }
        });
        match outcome {
            Ok(grant) => {
                request.extensions_mut().insert(Caller { grant, method });
                Either::Left(self.inner.call(request))
            }
            Err(status) => Either::Right(std::future::ready(Ok(status.into_http()))),
        }
    }
}

/// The grant of a call with the `authorization` header value on a connection whose client presented `certificate` (its
/// leaf, DER), or why it is not identified (UNAUTHENTICATED, counted).
fn identify(
    identities: &Identities,
    authorization: Option<&str>,
    certificate: Option<&[u8]>,
) -> Result<Arc<Grant>, Status> {
    if identities.open() {
        return Ok(Arc::new(Grant::admin("anonymous")));
    }
    let by_certificate = certificate
        .map(|der| certificate_grant(identities, der))
        .transpose()?;
    let token = authorization.and_then(bearer_token);
    match (token, by_certificate) {
        (Some(token), _) => token_grant(identities, token),
        (None, Some(grant)) => Ok(grant),
        (None, None) => Err(unauthenticated(
            "missing bearer token or client certificate",
        )),
    }
}

/// The grant of a bearer token: the single admin token, or one the roles file lists.
fn token_grant(identities: &Identities, token: &str) -> Result<Arc<Grant>, Status> {
    let digest = sha256_hex(token.as_bytes());
    let roles = identities.roles.as_ref();
    if roles.is_some_and(|r| r.denied_token_sha256.contains(&digest)) {
        return Err(unauthenticated("the bearer token is revoked"));
    }
    if let Some(admin) = &identities.admin_token
        && tokens_match(token, admin)
    {
        return Ok(Arc::new(Grant::admin("admin-token")));
    }
    roles
        .and_then(|r| r.tokens.get(&digest))
        .map(|grant| Arc::new(grant.clone()))
        .ok_or_else(|| unauthenticated("missing or wrong bearer token"))
}

/// The grant of a client certificate: as the roles file lists it, else the vehicle it names.
fn certificate_grant(identities: &Identities, der: &[u8]) -> Result<Arc<Grant>, Status> {
    let name = certificate_name(der).ok_or_else(|| {
        unauthenticated("the client certificate names no subject CN and no DNS SAN")
    })?;
    if let Some(roles) = &identities.roles {
        if roles.denied_certificate_names.contains(&name)
            || roles.denied_certificate_sha256.contains(&sha256_hex(der))
        {
            return Err(unauthenticated(&format!(
                "the client certificate {name:?} is revoked"
            )));
        }
        if let Some(grant) = roles.certificates.get(&name) {
            return Ok(Arc::new(grant.clone()));
        }
    }
    spoofwatch_proto::wire::VehicleId::parse(&name).map_err(|e| {
        unauthenticated(&format!(
            "the client certificate {name:?} is not in the roles file and names no vehicle: {e}"
        ))
    })?;
    Ok(Arc::new(Grant::vehicle(&name)))
}

/// A certificate's name: its subject's first CN, else its first DNS subject alternative name.
fn certificate_name(der: &[u8]) -> Option<String> {
    let (_, certificate) = x509_parser::parse_x509_certificate(der).ok()?;
    if let Some(cn) = certificate
        .subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
    {
        return Some(cn.to_string());
    }
    let names = certificate.subject_alternative_name().ok()??;
    names
        .value
        .general_names
        .iter()
        .find_map(|name| match name {
            x509_parser::extensions::GeneralName::DNSName(dns) => Some(dns.to_string()),
            _ => None,
        })
}

fn unauthenticated(reason: &str) -> Status {
    telemetry::unauthenticated();
    Status::new(Code::Unauthenticated, reason)
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
    use crate::access::roles::{Role, Roles, VehicleScope};

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

    fn with_token(token: &str) -> Option<String> {
        Some(format!("Bearer {token}"))
    }

    #[test]
    fn tokens_are_the_admin_token_or_listed_by_digest_and_a_revoked_one_fails() {
        let digest = sha256_hex(b"gw-token");
        let roles = Roles::parse(&format!(
            "[tokens]\n\"{digest}\" = {{ name = \"gw\", role = \"gateway\", vehicle_prefixes = [\"eu-\"] }}\n\
             [deny]\ntokens_sha256 = [\"{}\"]",
            sha256_hex(b"old-admin")
        ))
        .expect("valid");
        let identities = Identities {
            admin_token: Some("admin-secret".into()),
            roles: Some(roles),
            mutual_tls: false,
        };
        let admin =
            identify(&identities, with_token("admin-secret").as_deref(), None).expect("admin");
        assert_eq!(admin.role, Role::Admin);
        let gateway =
            identify(&identities, with_token("gw-token").as_deref(), None).expect("gateway");
        assert_eq!((&*gateway.name, gateway.role), ("gw", Role::Gateway));
        for refused in [with_token("nope"), with_token("old-admin"), None] {
            let status = identify(&identities, refused.as_deref(), None).expect_err("refused");
            assert_eq!(status.code(), Code::Unauthenticated);
        }
        let open = identify(&Identities::default(), None, None).expect("open");
        assert_eq!(open.scope, VehicleScope::All);
    }
}
