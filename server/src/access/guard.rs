//! The guard in front of every API service: identifies each call's caller, refuses the call when
//! its role may not make it, and hands the [`Caller`] to the service in the request's extensions.
//! It owns identification (bearer tokens by digest in constant time, client certificates by name
//! and fingerprint) and nothing else: the [`Caller`] keeps what was presented, and
//! `super::standing` identifies it again with [`identify`] when the identities change.
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
use super::{Access, Caller, Credential, Grant, Identities, denied};
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
        let certificate = request
            .extensions()
            .get::<TlsConnectInfo<TcpConnectInfo>>()
            .and_then(TlsConnectInfo::peer_certs);
        let admitted = self.access.admit(
            request.uri().path(),
            request
                .headers()
                .get("authorization")
                .and_then(|v| v.to_str().ok()),
            certificate
                .as_ref()
                .and_then(|chain| chain.first())
                .map(|c| c.as_ref()),
        );
        match admitted {
            Ok(caller) => {
                request.extensions_mut().insert(caller);
                Either::Left(self.inner.call(request))
            }
            Err(status) => Either::Right(std::future::ready(Ok(status.into_http()))),
        }
    }
}

impl Access {
    /// The caller of a call to `path` with the `authorization` header value on a connection whose
    /// client presented `certificate` (its leaf, DER), under the identities in force; or why it
    /// is refused (UNAUTHENTICATED, or PERMISSION_DENIED when its role may not make the call;
    /// counted).
    pub fn admit(
        &self,
        path: &str,
        authorization: Option<&str>,
        certificate: Option<&[u8]>,
    ) -> Result<Caller, Status> {
        let (method, need) = need_of(path);
        // Subscribed first and marked seen at the set the caller is identified by: a change after
        // this one is a change for the open call.
        let mut identities = self.current.subscribe();
        let current = Arc::clone(&identities.borrow_and_update());
        let presented = if current.open() {
            Presented::default()
        } else {
            Presented::of(authorization, certificate)
        };
        let grant = identify(&current, &presented)?;
        if !need.allows(grant.role) {
            return Err(denied(
                &grant,
                method,
                &format!("{method} (it needs {need:?})"),
            ));
        }
        let credential = presented.credential(&current, &grant);
        Ok(Caller {
            credential,
            grant,
            method,
            need,
            presented,
            identities,
        })
    }
}

/// What a call presented, kept by its [`Caller`] to be identified again when the identities
/// change: the bearer token's digest (never the token) and the client certificate's name and
/// digest.
#[derive(Clone, Debug, Default)]
pub(super) struct Presented {
    /// The SHA-256 (lower-case hex) of the `Bearer` token.
    token_sha256: Option<String>,
    certificate: Option<PresentedCertificate>,
}

#[derive(Clone, Debug)]
struct PresentedCertificate {
    /// Its subject's first CN, else its first DNS SAN (`None`: it names neither).
    name: Option<String>,
    /// The SHA-256 (lower-case hex) of its DER.
    sha256: String,
}

impl Presented {
    /// What the `authorization` header value and the client certificate (its leaf, DER) present.
    fn of(authorization: Option<&str>, certificate: Option<&[u8]>) -> Presented {
        Presented {
            token_sha256: authorization
                .and_then(bearer_token)
                .map(|token| sha256_hex(token.as_bytes())),
            certificate: certificate.map(|der| PresentedCertificate {
                name: certificate_name(der),
                sha256: sha256_hex(der),
            }),
        }
    }
}

/// How many hex digits of a credential's digest its label shows (64 bits: enough to tell apart
/// any two credentials of one fleet).
const LABEL_DIGEST_HEX: usize = 16;

impl Presented {
    /// The credential that identified this caller as `grant` under `identities` (the token when
    /// both a token and a certificate were presented, as [`identify`] decides).
    pub(super) fn credential(&self, identities: &Identities, grant: &Grant) -> Credential {
        if identities.open() {
            return Credential::unauthenticated();
        }
        let short = |digest: &str| digest.chars().take(LABEL_DIGEST_HEX).collect::<String>();
        let label = match (&self.token_sha256, &self.certificate) {
            (Some(digest), _)
                if identities
                    .admin_token_sha256
                    .as_deref()
                    .is_some_and(|admin| digests_match(digest, admin)) =>
            {
                "admin token".to_string()
            }
            (Some(digest), _) => format!("token {} sha256:{}", grant.name, short(digest)),
            (None, Some(certificate)) => format!(
                "certificate {} sha256:{}",
                certificate.name.as_deref().unwrap_or(&grant.name),
                short(&certificate.sha256)
            ),
            (None, None) => return Credential::unauthenticated(),
        };
        Credential {
            label: Arc::from(label),
            per_vehicle: grant.independent_receivers,
        }
    }
}

/// The grant of what a call `presented` under `identities`, or why it is not identified
/// (UNAUTHENTICATED, counted).
pub(super) fn identify(
    identities: &Identities,
    presented: &Presented,
) -> Result<Arc<Grant>, Status> {
    if identities.open() {
        return Ok(Arc::new(Grant::admin("anonymous")));
    }
    let by_certificate = presented
        .certificate
        .as_ref()
        .map(|certificate| certificate_grant(identities, certificate))
        .transpose()?;
    match (&presented.token_sha256, by_certificate) {
        (Some(digest), _) => token_grant(identities, digest),
        (None, Some(grant)) => Ok(grant),
        (None, None) => Err(unauthenticated(
            "missing bearer token or client certificate",
        )),
    }
}

/// The grant of a bearer token by its `digest`: the single admin token, or one the roles file
/// lists.
fn token_grant(identities: &Identities, digest: &str) -> Result<Arc<Grant>, Status> {
    let roles = identities.roles.as_ref();
    if roles.is_some_and(|r| r.denied_token_sha256.contains(digest)) {
        return Err(unauthenticated("the bearer token is revoked"));
    }
    if let Some(admin) = &identities.admin_token_sha256
        && digests_match(digest, admin)
    {
        return Ok(Arc::new(Grant::admin("admin-token")));
    }
    roles
        .and_then(|r| r.tokens.get(digest))
        .map(|grant| Arc::new(grant.clone()))
        .ok_or_else(|| unauthenticated("missing or wrong bearer token"))
}

/// The grant of a client certificate: as the roles file lists it, else the vehicle it names.
fn certificate_grant(
    identities: &Identities,
    certificate: &PresentedCertificate,
) -> Result<Arc<Grant>, Status> {
    let name = certificate.name.as_deref().ok_or_else(|| {
        unauthenticated("the client certificate names no subject CN and no DNS SAN")
    })?;
    if let Some(roles) = &identities.roles {
        if roles.denied_certificate_names.contains(name)
            || roles
                .denied_certificate_sha256
                .contains(&certificate.sha256)
        {
            return Err(unauthenticated(&format!(
                "the client certificate {name:?} is revoked"
            )));
        }
        if let Some(grant) = roles.certificates.get(name) {
            return Ok(Arc::new(grant.clone()));
        }
    }
    spoofwatch_proto::wire::VehicleId::parse(name).map_err(|e| {
        unauthenticated(&format!(
            "the client certificate {name:?} is not in the roles file and names no vehicle: {e}"
        ))
    })?;
    Ok(Arc::new(Grant::vehicle(name)))
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

/// Compares in time independent of where the digests differ (their length is not secret).
fn digests_match(presented: &str, expected: &str) -> bool {
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
        assert!(digests_match("abc", "abc"));
        assert!(!digests_match("abd", "abc"));
        assert!(!digests_match("", "abc"));
        assert!(!digests_match("abcd", "abc"));
    }

    fn with_token(token: &str) -> Presented {
        Presented::of(Some(&format!("Bearer {token}")), None)
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
            admin_token_sha256: Some(sha256_hex(b"admin-secret")),
            roles: Some(roles),
            mutual_tls: false,
        };
        let admin = identify(&identities, &with_token("admin-secret")).expect("admin");
        assert_eq!(admin.role, Role::Admin);
        let gateway = identify(&identities, &with_token("gw-token")).expect("gateway");
        assert_eq!((&*gateway.name, gateway.role), ("gw", Role::Gateway));
        for refused in [
            with_token("nope"),
            with_token("old-admin"),
            Presented::default(),
        ] {
            let status = identify(&identities, &refused).expect_err("refused");
            assert_eq!(status.code(), Code::Unauthenticated);
        }
        let open = identify(&Identities::default(), &Presented::default()).expect("open");
        assert_eq!(open.scope, VehicleScope::All);
    }

    /// The credential an alarm records names what identified the caller, never the secret: the
    /// roles file's token name and digest prefix, the admin token, a certificate's name and
    /// digest prefix, or `unauthenticated` on a server without identities.
    #[test]
    fn the_credential_names_what_identified_the_caller_and_never_its_secret() {
        let digest = sha256_hex(b"gw-token");
        let roles = Roles::parse(&format!(
            "[tokens]\n\"{digest}\" = {{ name = \"gw\", role = \"gateway\", vehicle_prefixes = [\"eu-\"] }}\n\
             [certificates]\n\"truck-7\" = {{ role = \"vehicle\" }}\n"
        ))
        .expect("valid");
        let identities = Identities {
            admin_token_sha256: Some(sha256_hex(b"admin-secret")),
            roles: Some(roles),
            mutual_tls: true,
        };
        let label = |presented: &Presented| {
            let grant = identify(&identities, presented).expect("identified");
            let credential = presented.credential(&identities, &grant);
            (credential.label.to_string(), credential.per_vehicle)
        };
        assert_eq!(
            label(&with_token("gw-token")),
            (format!("token gw sha256:{}", &digest[..16]), false)
        );
        assert_eq!(
            label(&with_token("admin-secret")),
            ("admin token".to_string(), false)
        );
        let certificate = Presented {
            token_sha256: None,
            certificate: Some(PresentedCertificate {
                name: Some("truck-7".to_string()),
                sha256: "ab".repeat(32),
            }),
        };
        assert_eq!(
            label(&certificate),
            (
                "certificate truck-7 sha256:abababababababab".to_string(),
                false
            )
        );
        for (text, _) in [label(&with_token("gw-token")), label(&certificate)] {
            assert!(
                !text.contains("gw-token") && !text.contains(&digest),
                "{text}"
            );
        }
        let open = Identities::default();
        let grant = identify(&open, &with_token("anything")).expect("open");
        assert_eq!(
            with_token("anything").credential(&open, &grant),
            Credential::unauthenticated()
        );
    }
}
