//! The identity files, read at start and re-read when they change: the roles file and the file of
//! the single admin token. A change is picked up within [`POLL`] without a restart (a Kubernetes
//! Secret or ConfigMap update included), for new calls and for the calls already open (each is
//! told through [`Access`]'s channel and judged again by `super::standing`); a changed file that
//! cannot be read or parsed is logged and counted, and the identities in force stay. It owns the
//! reading, not the checks.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use super::{Access, Identities, Roles, Sources};
use crate::identity::sha256_hex;
use crate::telemetry;

/// How often the files are looked at.
pub const POLL: Duration = Duration::from_secs(2);

/// The identities of `sources`, every file read now.
pub fn read(sources: &Sources) -> Result<Identities, String> {
    if sources.token.is_some() && sources.token_file.is_some() {
        return Err(
            "SPOOFWATCH_AUTH_TOKEN and --auth-token-file both set: give the admin token once"
                .into(),
        );
    }
    let admin_token = match (&sources.token, &sources.token_file) {
        (Some(token), _) => {
            Some(parse_token(token).map_err(|e| format!("SPOOFWATCH_AUTH_TOKEN: {e}"))?)
        }
        (None, Some(path)) => Some(read_token(path)?),
        (None, None) => None,
    };
    let roles = sources.roles_file.as_deref().map(read_roles).transpose()?;
    Ok(Identities {
        admin_token_sha256: admin_token.map(|token| sha256_hex(token.as_bytes())),
        roles,
        mutual_tls: sources.mutual_tls,
    })
}

/// A bearer token: 1–4,096 visible ASCII characters (what an `authorization` header can carry).
/// An empty token would make "no token" and "the token" the same, so it is a configuration error.
fn parse_token(text: &str) -> Result<String, String> {
    if text.is_empty() {
        return Err("must not be empty (leave it unset to serve without a token)".into());
    }
    if text.len() > 4096 || !text.bytes().all(|b| b.is_ascii_graphic()) {
        return Err("must be at most 4096 visible ASCII characters, without spaces".into());
    }
    Ok(text.to_string())
}

fn read_token(path: &Path) -> Result<String, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("--auth-token-file {}: cannot read: {e}", path.display()))?;
    // Files written by `echo` or an editor end with a newline; it is not part of the token.
    parse_token(text.trim_end_matches(['\n', '\r']))
        .map_err(|e| format!("--auth-token-file {}: {e}", path.display()))
}

fn read_roles(path: &Path) -> Result<Roles, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("--roles-file {}: cannot read: {e}", path.display()))?;
    Roles::parse(&text).map_err(|e| format!("--roles-file {}: {e}", path.display()))
}

/// The files' bytes, to tell a change (`None` for an unreadable file).
fn fingerprint(sources: &Sources) -> Vec<Option<Vec<u8>>> {
    [&sources.token_file, &sources.roles_file]
        .into_iter()
        .flatten()
        .map(|path| std::fs::read(path).ok())
        .collect()
}

/// Re-reads `access`'s files every [`POLL`] and puts changed identities in force, until `stop`.
pub async fn keep_current(access: Arc<Access>, stop: CancellationToken) {
    if access.sources.token_file.is_none() && access.sources.roles_file.is_none() {
        return;
    }
    let mut last = fingerprint(&access.sources);
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = tokio::time::sleep(POLL) => {}
        }
        let sources = access.sources.clone();
        let Ok((now, read)) = tokio::task::spawn_blocking(move || {
            let now = fingerprint(&sources);
            let read = read(&sources);
            (now, read)
        })
        .await
        else {
            continue;
        };
        if now == last {
            continue;
        }
        last = now;
        match read {
            Ok(identities) => {
                access.replace(identities);
                telemetry::identities_reloaded(true);
                tracing::info!(identities = %access.describe(), "identity files reloaded");
            }
            Err(error) => {
                telemetry::identities_reloaded(false);
                tracing::error!(%error, "identity files changed but cannot be used; the previous identities stay in force");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_or_unprintable_token_is_refused() {
        for bad in ["", "two words", "tab\there", "é"] {
            assert!(parse_token(bad).is_err(), "{bad:?}");
        }
        assert_eq!(parse_token("s3cr3t-T0ken").as_deref(), Ok("s3cr3t-T0ken"));
    }

    #[test]
    fn the_token_file_loses_its_newline_and_two_tokens_are_refused() {
        let dir = tempfile::tempdir().expect("temp dir");
        let token_file = dir.path().join("token");
        std::fs::write(&token_file, "s3cret\n").expect("written");
        let sources = Sources {
            token_file: Some(token_file.clone()),
            ..Sources::default()
        };
        assert_eq!(
            read(&sources).expect("readable").admin_token_sha256,
            Some(sha256_hex(b"s3cret"))
        );
        let both = Sources {
            token: Some("x".into()),
            ..sources
        };
        assert!(read(&both).expect_err("two tokens").contains("both set"));
        std::fs::write(&token_file, "\n").expect("written");
        let empty = Sources {
            token_file: Some(token_file),
            ..Sources::default()
        };
        assert!(
            read(&empty)
                .expect_err("empty")
                .contains("must not be empty")
        );
    }
}
