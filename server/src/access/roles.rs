//! The roles file: which client certificates and which bearer tokens act as which role, and which
//! are revoked. Parsed and checked here into [`Roles`], with errors that name the entry and the
//! field; it reads no file and knows no request (`super::guard` applies it, `super::reload`
//! reads it).
//!
//! ```toml
//! [certificates]            # by the subject's CN (or first DNS SAN)
//! "gateway-eu-1" = { role = "gateway", vehicle_prefixes = ["eu-"] }
//! "ops-dashboard" = { role = "operator" }
//! "relay-1" = { role = "gateway", vehicle_prefixes = ["fleet-"], independent_receivers = true }
//!
//! [tokens]                  # by the token's SHA-256 (hex): the file holds no secret
//! "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08" = { name = "backend-1", role = "admin" }
//!
//! [deny]                    # revoked, even though the CA signed them or the token is listed
//! certificates = ["truck-13"]
//! certificate_sha256 = []   # SHA-256 of a certificate's DER, for one certificate of a name
//! tokens_sha256 = []
//! ```
//!
//! It fails closed: a file that lists nothing (an editor's truncation, a ConfigMap caught
//! mid-update) is refused unless it says `empty = true`; a gateway of the whole fleet says
//! `all_vehicles = true` rather than an empty prefix; a token digest listed twice, in two letter
//! cases, is refused rather than one grant silently replacing the other.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

use serde::Deserialize;
use spoofwatch_proto::wire::VehicleId;

/// What a caller may do (see `super::policy` for the calls of each).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// The detection calls, for its own vehicle only.
    Vehicle,
    /// The detection calls, for a configured set or prefix of vehicles.
    Gateway,
    /// Reads alarms, sessions, models, datasets and jobs; changes nothing.
    Operator,
    /// Everything: models, datasets, jobs, roll-out, resets, and detection for any vehicle.
    Admin,
}

impl Role {
    #[cfg(test)]
    pub const ALL: [Role; 4] = [Role::Vehicle, Role::Gateway, Role::Operator, Role::Admin];

    pub fn as_str(self) -> &'static str {
        match self {
            Role::Vehicle => "vehicle",
            Role::Gateway => "gateway",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }
}

/// The vehicles a caller may detect for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum VehicleScope {
    /// Every vehicle (an admin).
    All,
    /// None (an operator: it reads, it does not stream).
    None,
    /// These ids, and every id that starts with one of these prefixes.
    Some {
        ids: HashSet<String>,
        prefixes: Vec<String>,
    },
}

impl VehicleScope {
    /// Only `id`: a vehicle's own scope.
    pub fn one(id: &str) -> Self {
        VehicleScope::Some {
            ids: HashSet::from([id.to_string()]),
            prefixes: Vec::new(),
        }
    }

    pub fn contains(&self, vehicle_id: &str) -> bool {
        match self {
            VehicleScope::All => true,
            VehicleScope::None => false,
            VehicleScope::Some { ids, prefixes } => {
                ids.contains(vehicle_id) || prefixes.iter().any(|p| vehicle_id.starts_with(p))
            }
        }
    }
}

/// One identity's grant: its name (logged with every refusal), role and vehicles.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Grant {
    pub name: Arc<str>,
    pub role: Role,
    pub scope: VehicleScope,
    /// A gateway that forwards independent receivers: each of its vehicles is its own source of
    /// evidence for area incidents (otherwise all of them are one).
    pub independent_receivers: bool,
}

impl Grant {
    /// `role` for `name`; a gateway's scope is given, the others' follow from the role (a
    /// vehicle's is its own name).
    fn new(name: &str, role: Role, scope: VehicleScope) -> Self {
        let scope = match role {
            Role::Vehicle => VehicleScope::one(name),
            Role::Gateway => scope,
            Role::Operator => VehicleScope::None,
            Role::Admin => VehicleScope::All,
        };
        Grant {
            name: Arc::from(name),
            role,
            scope,
            independent_receivers: false,
        }
    }

    /// The admin of the single configured token (`SPOOFWATCH_AUTH_TOKEN` or its file).
    pub fn admin(name: &str) -> Self {
        Grant::new(name, Role::Admin, VehicleScope::All)
    }

    /// The default of a client certificate the roles file does not list: the vehicle it names.
    pub fn vehicle(name: &str) -> Self {
        Grant::new(name, Role::Vehicle, VehicleScope::None)
    }
}

/// The roles file, parsed and checked.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Roles {
    /// By certificate name (CN or first DNS SAN).
    pub certificates: HashMap<String, Grant>,
    /// By the token's SHA-256, lower-case hex.
    pub tokens: HashMap<String, Grant>,
    pub denied_certificate_names: HashSet<String>,
    pub denied_certificate_sha256: HashSet<String>,
    pub denied_token_sha256: HashSet<String>,
}

/// Why a roles file cannot be used; the previous roles stay in force.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum RolesError {
    #[error("not a valid roles file: {0}")]
    Syntax(String),
    #[error("{entry}: {problem}")]
    Entry { entry: String, problem: String },
    #[error(
        "the roles file lists no identity and no revocation (a truncated file?); write \
         `empty = true` to serve with none on purpose"
    )]
    Empty,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    /// Says that a file listing no identity and no revocation means it.
    #[serde(default)]
    empty: bool,
    #[serde(default)]
    certificates: BTreeMap<String, Entry>,
    #[serde(default)]
    tokens: BTreeMap<String, Entry>,
    #[serde(default)]
    deny: Deny,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    role: Role,
    /// A token's name in logs (a certificate's is its own name).
    name: Option<String>,
    #[serde(default)]
    vehicles: Vec<String>,
    #[serde(default)]
    vehicle_prefixes: Vec<String>,
    /// A gateway for every vehicle of the fleet.
    #[serde(default)]
    all_vehicles: bool,
    /// A gateway that forwards independent receivers (each vehicle its own GNSS receiver and
    /// connection, the gateway only relaying): each of its vehicles counts as its own source of
    /// evidence for area incidents. Without it, all of a gateway's vehicles are one source.
    #[serde(default)]
    independent_receivers: bool,
}

#[derive(Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Deny {
    #[serde(default)]
    certificates: Vec<String>,
    #[serde(default)]
    certificate_sha256: Vec<String>,
    #[serde(default)]
    tokens_sha256: Vec<String>,
}

/// Longest name or prefix in the file (names are logged; vehicle ids are at most 128 bytes).
const MAX_NAME_BYTES: usize = 256;

impl Roles {
    /// Parses and checks a roles file's text.
    pub fn parse(text: &str) -> Result<Roles, RolesError> {
        let file: File = toml::from_str(text).map_err(|e| {
            // toml's message quotes the offending line; the first lines are enough.
            let message = e.to_string();
            RolesError::Syntax(message.lines().take(6).collect::<Vec<_>>().join("\n"))
        })?;
        check_emptiness(&file)?;
        let mut roles = Roles::default();
        for (name, entry) in file.certificates {
            let at = format!("certificates.{name:?}");
            check_name(&at, &name)?;
            if entry.name.is_some() {
                return Err(entry_error(
                    &at,
                    "name: a certificate's name is its key (its subject's CN or first DNS SAN)",
                ));
            }
            if entry.role == Role::Vehicle {
                VehicleId::parse(&name)
                    .map_err(|e| entry_error(&at, format!("not a vehicle id: {e}")))?;
            }
            let grant = grant_of(&at, &name, &entry)?;
            roles.certificates.insert(name, grant);
        }
        // Each digest as written, by its lower-case form.
        let mut seen_digests: HashMap<String, String> = HashMap::new();
        for (digest, entry) in file.tokens {
            let at = format!("tokens.{digest:?}");
            check_sha256(&at, &digest)?;
            let name = entry.name.clone().ok_or_else(|| {
                entry_error(&at, "name: required (the token's name in logs and metrics)")
            })?;
            check_name(&format!("{at}.name"), &name)?;
            if entry.role == Role::Vehicle {
                VehicleId::parse(&name).map_err(|e| {
                    entry_error(
                        &at,
                        format!("name: a vehicle token's name is its vehicle id: {e}"),
                    )
                })?;
            }
            let grant = grant_of(&at, &name, &entry)?;
            let key = digest.to_ascii_lowercase();
            if let Some(other) = seen_digests.get(&key) {
                return Err(entry_error(
                    &format!(
                        "tokens.{other:?} (line {}) and {at} (line {})",
                        line_of(text, other),
                        line_of(text, &digest)
                    ),
                    "the same token digest listed twice, in other letter cases (digests are \
                     compared without case): keep one entry",
                ));
            }
            seen_digests.insert(key.clone(), digest.clone());
            roles.tokens.insert(key, grant);
        }
        for (i, name) in file.deny.certificates.into_iter().enumerate() {
            check_name(&format!("deny.certificates[{i}]"), &name)?;
            roles.denied_certificate_names.insert(name);
        }
        for (i, digest) in file.deny.certificate_sha256.into_iter().enumerate() {
            check_sha256(&format!("deny.certificate_sha256[{i}]"), &digest)?;
            roles
                .denied_certificate_sha256
                .insert(digest.to_ascii_lowercase());
        }
        for (i, digest) in file.deny.tokens_sha256.into_iter().enumerate() {
            check_sha256(&format!("deny.tokens_sha256[{i}]"), &digest)?;
            roles
                .denied_token_sha256
                .insert(digest.to_ascii_lowercase());
        }
        Ok(roles)
    }
}

/// A file that grants and revokes nothing is refused unless it says `empty = true`, and one that
/// says so must list nothing: a truncated file must not put an empty policy in force.
fn check_emptiness(file: &File) -> Result<(), RolesError> {
    let lists_nothing = file.certificates.is_empty()
        && file.tokens.is_empty()
        && file.deny.certificates.is_empty()
        && file.deny.certificate_sha256.is_empty()
        && file.deny.tokens_sha256.is_empty();
    match (lists_nothing, file.empty) {
        (true, false) => Err(RolesError::Empty),
        (false, true) => Err(entry_error(
            "empty",
            "`empty = true` says the file lists nothing, but it lists identities or revocations",
        )),
        _ => Ok(()),
    }
}

/// The 1-based line of the first line of `text` whose key is `"key"` (0 when none is).
fn line_of(text: &str, key: &str) -> usize {
    let quoted = format!("\"{key}\"");
    text.lines()
        .position(|line| line.trim_start().starts_with(&quoted))
        .map_or(0, |index| index + 1)
}

/// The grant of the entry at `at` for `name`: its role, its scope, and whether it forwards
/// independent receivers (a gateway's choice only).
fn grant_of(at: &str, name: &str, entry: &Entry) -> Result<Grant, RolesError> {
    if entry.independent_receivers && entry.role != Role::Gateway {
        return Err(entry_error(
            at,
            format!(
                "independent_receivers: only a gateway forwards receivers (this entry's role is {}: \
                 one source)",
                entry.role.as_str()
            ),
        ));
    }
    Ok(Grant {
        independent_receivers: entry.independent_receivers,
        ..Grant::new(name, entry.role, scope_of(at, entry)?)
    })
}

/// A gateway's vehicles; the other roles must not list any (their scope follows from the role).
fn scope_of(at: &str, entry: &Entry) -> Result<VehicleScope, RolesError> {
    let listed = !entry.vehicles.is_empty() || !entry.vehicle_prefixes.is_empty();
    match entry.role {
        Role::Gateway if entry.all_vehicles && listed => Err(entry_error(
            at,
            "all_vehicles: a gateway for every vehicle lists no `vehicles` or `vehicle_prefixes`",
        )),
        Role::Gateway if entry.all_vehicles => Ok(VehicleScope::All),
        Role::Gateway if !listed => Err(entry_error(
            at,
            "a gateway needs `vehicles`, `vehicle_prefixes` or `all_vehicles = true` (the \
             vehicles it may stream for)",
        )),
        Role::Gateway => {
            for (i, id) in entry.vehicles.iter().enumerate() {
                VehicleId::parse(id).map_err(|e| entry_error(at, format!("vehicles[{i}]: {e}")))?;
            }
            for (i, prefix) in entry.vehicle_prefixes.iter().enumerate() {
                if prefix.is_empty() {
                    return Err(entry_error(
                        at,
                        format!(
                            "vehicle_prefixes[{i}]: an empty prefix would grant every vehicle; \
                             write `all_vehicles = true` to mean that"
                        ),
                    ));
                }
                check_name(&format!("{at}.vehicle_prefixes[{i}]"), prefix)?;
            }
            Ok(VehicleScope::Some {
                ids: entry.vehicles.iter().cloned().collect(),
                prefixes: entry.vehicle_prefixes.clone(),
            })
        }
        role if listed || entry.all_vehicles => Err(entry_error(
            at,
            format!(
                "only a gateway lists vehicles (a {} has its scope by its role)",
                role.as_str()
            ),
        )),
        _ => Ok(VehicleScope::None),
    }
}

fn check_name(at: &str, name: &str) -> Result<(), RolesError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(entry_error(
            at,
            format!("must be 1 to {MAX_NAME_BYTES} bytes without control characters"),
        ));
    }
    Ok(())
}

fn check_sha256(at: &str, digest: &str) -> Result<(), RolesError> {
    if digest.len() != 64 || !digest.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(entry_error(
            at,
            "must be a SHA-256 in hex (64 characters; e.g. `printf %s \"$TOKEN\" | sha256sum`)",
        ));
    }
    Ok(())
}

fn entry_error(entry: &str, problem: impl Into<String>) -> RolesError {
    RolesError::Entry {
        entry: entry.to_string(),
        problem: problem.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIGEST: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

    #[test]
    fn the_documented_example_parses_into_its_grants() {
        let roles = Roles::parse(&format!(
            r#"
            [certificates]
            "gateway-eu-1" = {{ role = "gateway", vehicle_prefixes = ["eu-"], vehicles = ["car-9"] }}
            "ops-dashboard" = {{ role = "operator" }}
            "truck-7" = {{ role = "vehicle" }}
            [tokens]
            "{}" = {{ name = "backend-1", role = "admin" }}
            [deny]
            certificates = ["truck-13"]
            tokens_sha256 = ["{DIGEST}"]
            "#,
            DIGEST.to_ascii_uppercase()
        ))
        .expect("a valid file");
        let gateway = &roles.certificates["gateway-eu-1"];
        assert_eq!(gateway.role, Role::Gateway);
        assert!(gateway.scope.contains("eu-truck-1"));
        assert!(gateway.scope.contains("car-9"));
        assert!(!gateway.scope.contains("us-truck-1"));
        assert!(!gateway.scope.contains("car-90"));
        assert_eq!(
            roles.certificates["ops-dashboard"].scope,
            VehicleScope::None
        );
        assert_eq!(
            roles.certificates["truck-7"].scope,
            VehicleScope::one("truck-7")
        );
        let admin = &roles.tokens[DIGEST];
        assert_eq!((&*admin.name, admin.role), ("backend-1", Role::Admin));
        assert_eq!(admin.scope, VehicleScope::All);
        assert!(roles.denied_certificate_names.contains("truck-13"));
        assert!(roles.denied_token_sha256.contains(DIGEST));
    }

    #[test]
    fn a_file_that_lists_nothing_must_say_so() {
        for text in [
            "",
            "\n  \n",
            "# all commented out\n",
            "[certificates]\n[tokens]\n[deny]\n",
        ] {
            assert_eq!(Roles::parse(text), Err(RolesError::Empty), "{text:?}");
        }
        assert_eq!(Roles::parse("empty = true\n"), Ok(Roles::default()));
        let contradiction = "empty = true\n[deny]\ncertificates = [\"truck-13\"]\n";
        let error = Roles::parse(contradiction).expect_err("lists a revocation");
        assert!(error.to_string().starts_with("empty: "), "{error}");
    }

    #[test]
    fn a_digest_listed_in_two_cases_is_refused_naming_both_lines() {
        let text = format!(
            "[tokens]\n\"{}\" = {{ name = \"old\", role = \"admin\" }}\n\
             \"{DIGEST}\" = {{ name = \"new\", role = \"operator\" }}\n",
            DIGEST.to_ascii_uppercase()
        );
        let error = Roles::parse(&text).expect_err("a duplicate").to_string();
        assert!(
            error.contains("(line 2)") && error.contains("(line 3)"),
            "{error}"
        );
        assert!(error.contains("listed twice"), "{error}");
    }

    #[test]
    fn a_gateway_of_every_vehicle_says_all_vehicles() {
        let roles =
            Roles::parse("[certificates]\n\"gw\" = { role = \"gateway\", all_vehicles = true }\n")
                .expect("valid");
        assert_eq!(roles.certificates["gw"].scope, VehicleScope::All);
        let cases = [
            (
                "[certificates]\n\"gw\" = { role = \"gateway\", vehicle_prefixes = [\"\"] }",
                "vehicle_prefixes[0]: an empty prefix would grant every vehicle",
            ),
            (
                "[certificates]\n\"gw\" = { role = \"gateway\", all_vehicles = true, vehicles = [\"a\"] }",
                "all_vehicles: a gateway for every vehicle lists no",
            ),
            (
                "[certificates]\n\"op\" = { role = \"operator\", all_vehicles = true }",
                "only a gateway lists vehicles",
            ),
        ];
        for (text, expected) in cases {
            let error = Roles::parse(text).expect_err(text).to_string();
            assert!(error.contains(expected), "{text:?}: {error}");
        }
    }

    #[test]
    fn the_roles_file_of_the_operating_guide_parses() {
        let guide = include_str!("../../../docs/operating.md");
        let start = guide.find("```toml\n").expect("a TOML example") + "```toml\n".len();
        let end = start + guide[start..].find("```").expect("its end");
        let roles = Roles::parse(&guide[start..end]).expect("the documented file is valid");
        assert_eq!(roles.certificates["gateway-eu-1"].role, Role::Gateway);
        let example = crate::identity::sha256_hex(b"example-token");
        assert_eq!(&*roles.tokens[&example].name, "backend-1");
        assert!(roles.denied_certificate_names.contains("truck-13"));
    }

    #[test]
    fn only_a_gateway_may_say_it_forwards_independent_receivers() {
        let roles = Roles::parse(
            "[certificates]\n\"relay\" = { role = \"gateway\", all_vehicles = true, \
             independent_receivers = true }\n\"gw\" = { role = \"gateway\", all_vehicles = true }\n",
        )
        .expect("valid");
        assert!(roles.certificates["relay"].independent_receivers);
        assert!(!roles.certificates["gw"].independent_receivers);
        let cases = [
            (
                "[certificates]\n\"car-1\" = { role = \"vehicle\", independent_receivers = true }",
                "certificates.\"car-1\": independent_receivers: only a gateway",
            ),
            (
                &format!(
                    "[tokens]\n\"{DIGEST}\" = {{ name = \"a\", role = \"admin\", independent_receivers = true }}"
                ),
                "independent_receivers: only a gateway forwards receivers (this entry's role is admin",
            ),
            (
                "[certificates]\n\"gw\" = { role = \"gateway\", all_vehicles = true, independent_receiver = true }",
                "not a valid roles file",
            ),
        ];
        for (text, expected) in cases {
            let error = Roles::parse(text).expect_err(text).to_string();
            assert!(error.contains(expected), "{text:?}: {error}");
        }
    }

    #[test]
    fn a_wrong_entry_is_named_with_its_problem() {
        let cases = [
            (
                "[certificates]\n\"gw\" = { role = \"gateway\" }",
                "certificates.\"gw\": a gateway needs",
            ),
            (
                "[certificates]\n\"op\" = { role = \"operator\", vehicles = [\"a\"] }",
                "only a gateway lists vehicles",
            ),
            (
                "[certificates]\n\"a b\" = { role = \"vehicle\" }",
                "not a vehicle id",
            ),
            (
                "[tokens]\n\"abc\" = { name = \"x\", role = \"admin\" }",
                "tokens.\"abc\": must be a SHA-256",
            ),
            (
                &format!("[tokens]\n\"{DIGEST}\" = {{ role = \"admin\" }}"),
                "name: required",
            ),
            (
                "[certificates]\n\"x\" = { role = \"root\" }",
                "not a valid roles file",
            ),
            ("[deny]\ncertificate = [\"x\"]", "not a valid roles file"),
            (
                "[deny]\ncertificate_sha256 = [\"zz\"]",
                "deny.certificate_sha256[0]",
            ),
        ];
        for (text, expected) in cases {
            let error = Roles::parse(text).expect_err(text).to_string();
            assert!(error.contains(expected), "{text:?}: {error}");
        }
    }
}
