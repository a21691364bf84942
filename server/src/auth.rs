//! Who is calling: bearer tokens for operators, viewers and robots, checked
//! in one layer before any handler runs.
//!
//! [`AuthLayer`] is a tonic interceptor on both services: it authenticates
//! every call and puts the [`Caller`] into the request's extensions, so a
//! handler only authorises (`require_operator`, `require_robot`) and cannot
//! forget to authenticate. The services are only served behind it
//! ([`crate::service::ExplorationService::into_servers`]).
//!
//! Operators hold named tokens, each with a role: `operator` may do
//! everything, `viewer` may only read. They come from `--operator-token` (one
//! token, named "operator") and from a tokens file (`--operator-tokens`),
//! which is read again whenever it changes, so a token can be revoked without
//! a restart; the name goes into the audit trail. A robot's token is issued at
//! registration and only its SHA-256 is kept; it reads
//! `rbt_<robot id>_<32 random bytes in hex>`, so that the hash to compare with
//! is found without scanning. Without any operator token the executive runs
//! open: every caller is an operator (loopback and tests).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};
use tonic::metadata::MetadataMap;

use crate::domain::RobotId;
use crate::error::Error;

/// What an operator token allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Everything.
    Operator,
    /// Reading only.
    Viewer,
}

impl Role {
    fn parse(s: &str) -> Option<Self> {
        match s {
            "operator" => Some(Self::Operator),
            "viewer" => Some(Self::Viewer),
            _ => None,
        }
    }
}

/// Who a request comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Caller {
    /// Anyone, on an executive that runs open: may do everything, and names
    /// itself in the audit trail.
    Anonymous,
    /// The holder of a named operator or viewer token.
    Operator {
        /// The token's name, recorded as the actor.
        name: String,
        /// What the token allows.
        role: Role,
    },
    /// A robot's own token.
    Robot(RobotId),
}

impl Caller {
    /// Only operators may administer missions and override robots.
    pub fn require_operator(&self, what: &str) -> Result<(), Error> {
        match self {
            Self::Anonymous | Self::Operator { role: Role::Operator, .. } => Ok(()),
            Self::Operator { name, role: Role::Viewer } => Err(Error::PermissionDenied(format!(
                "{what} needs an operator token; the token {name:?} is a viewer's, which may only read"
            ))),
            Self::Robot(id) => Err(Error::PermissionDenied(format!(
                "{what} needs the operator token; the token of robot {id} may only report as that robot and read"
            ))),
        }
    }

    /// A robot may act only as itself; operators as any robot.
    pub fn require_robot(&self, robot: RobotId) -> Result<(), Error> {
        match self {
            Self::Anonymous | Self::Operator { role: Role::Operator, .. } => Ok(()),
            Self::Robot(id) if *id == robot => Ok(()),
            Self::Operator { name, role: Role::Viewer } => Err(Error::PermissionDenied(format!(
                "the token {name:?} is a viewer's, which may only read; it may not act as robot {robot}"
            ))),
            Self::Robot(id) => Err(Error::PermissionDenied(format!(
                "the token of robot {id} may not act as robot {robot}; each robot uses the token its registration returned"
            ))),
        }
    }

    /// The name an operator action is recorded under: the token's name, or
    /// on an open executive the name the caller gave (`claimed`).
    pub fn actor(&self, claimed: &str) -> String {
        match self {
            Self::Operator { name, .. } => name.clone(),
            Self::Robot(id) => format!("robot {id}"),
            Self::Anonymous => claimed.to_owned(),
        }
    }
}

/// Why the operator tokens could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum TokensError {
    /// `--operator-token` was given but is blank.
    #[error("the operator token is empty: give a token of at least 16 characters, or none to run open")]
    Empty,
    /// A token too short to resist guessing.
    #[error("the operator token has {0} characters; give at least 16")]
    Short(usize),
    /// The tokens file could not be read.
    #[error("cannot read the tokens file {path}: {cause}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// A line of the tokens file is malformed.
    #[error("tokens file {path}, line {line}: {problem}")]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        problem: String,
    },
}

/// Shortest operator token accepted.
pub const MIN_TOKEN_CHARS: usize = 16;

/// A named operator or viewer token, by the SHA-256 of the token.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Holder {
    name: String,
    role: Role,
}

/// Parses a tokens file: one `NAME ROLE SHA256` per line (the hash of the
/// token in lower-case hex, as `printf %s TOKEN | sha256sum` prints it);
/// blank lines and `#` comments are skipped.
fn parse_tokens(path: &Path, text: &str) -> Result<HashMap<String, Holder>, TokensError> {
    let mut holders = HashMap::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let bad = |problem: String| TokensError::Line { path: path.to_owned(), line: number + 1, problem };
        let fields: Vec<&str> = line.split_whitespace().collect();
        let [name, role, hash] = fields[..] else {
            return Err(bad(format!("expected `NAME ROLE SHA256`, found {} fields", fields.len())));
        };
        let name = crate::validate::name(name, "the name").map_err(|e| bad(e.to_string()))?;
        let role = Role::parse(role).ok_or_else(|| bad(format!("role {role:?} is neither operator nor viewer")))?;
        let hash = hash.to_ascii_lowercase();
        if hash.len() != 64 || !hash.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(bad("the hash is not a SHA-256 in hex (64 digits)".to_owned()));
        }
        if holders.insert(hash, Holder { name: name.clone(), role }).is_some() {
            return Err(bad(format!("the hash of {name:?} repeats an earlier line's")));
        }
    }
    Ok(holders)
}

/// What identifies one version of the tokens file: a rewrite in place or a
/// rename over it changes one of these.
#[derive(Debug, Clone, PartialEq, Eq)]
struct FileVersion {
    modified: Option<std::time::SystemTime>,
    len: u64,
    inode: u64,
}

fn file_version(path: &Path) -> std::io::Result<FileVersion> {
    let meta = std::fs::metadata(path)?;
    #[cfg(unix)]
    let inode = std::os::unix::fs::MetadataExt::ino(&meta);
    #[cfg(not(unix))]
    let inode = 0;
    Ok(FileVersion { modified: meta.modified().ok(), len: meta.len(), inode })
}

/// The tokens file as last read.
#[derive(Debug)]
struct TokensFile {
    path: PathBuf,
    version: Option<FileVersion>,
    holders: HashMap<String, Holder>,
}

/// Most a tokens file may hold: a line per token, about a hundred bytes, so
/// some 160 000 tokens.
const TOKENS_FILE_MIB: u64 = 16;

impl TokensFile {
    fn load(path: &Path) -> Result<Self, TokensError> {
        let read = |cause| TokensError::Read { path: path.to_owned(), cause };
        let version = file_version(path).map_err(read)?;
        let text = crate::files::read_text_at_most(path, TOKENS_FILE_MIB).map_err(read)?;
        Ok(Self { path: path.to_owned(), version: Some(version), holders: parse_tokens(path, &text)? })
    }

    /// Reads the file again if it changed. A file that cannot be read or
    /// parsed any more admits nobody until it is fixed (failing closed), and
    /// says so in the log once per version.
    fn refresh(&mut self) {
        let version = file_version(&self.path).ok();
        if version == self.version {
            return;
        }
        self.version = version;
        match Self::load(&self.path) {
            Ok(fresh) => {
                tracing::info!(path = %self.path.display(), tokens = fresh.holders.len(), "operator tokens reloaded");
                self.holders = fresh.holders;
            }
            Err(e) => {
                tracing::error!(error = %e, "operator tokens file unusable: no token from it is accepted until fixed");
                self.holders.clear();
            }
        }
    }
}

/// Checks bearer tokens.
#[derive(Debug, Clone, Default)]
pub struct Authenticator {
    /// `--operator-token`'s hash, named "operator".
    single: Option<String>,
    file: Option<Arc<Mutex<TokensFile>>>,
}

impl Authenticator {
    /// Every caller is an operator: no token is checked.
    pub fn open() -> Self {
        Self::default()
    }

    /// Operator tokens from `--operator-token` and the tokens file; open
    /// when neither is given.
    pub fn new(token: Option<&str>, file: Option<&Path>) -> Result<Self, TokensError> {
        let single = match token {
            None => None,
            Some(t) if t.trim().is_empty() => return Err(TokensError::Empty),
            Some(t) if t.trim().chars().count() < MIN_TOKEN_CHARS => {
                return Err(TokensError::Short(t.trim().chars().count()));
            }
            Some(t) => Some(sha256_hex(t.trim())),
        };
        let file = file.map(TokensFile::load).transpose()?.map(|f| Arc::new(Mutex::new(f)));
        Ok(Self { single, file })
    }

    /// Requires `token` for operator calls and robot tokens for robots.
    pub fn with_operator_token(token: &str) -> Self {
        Self { single: Some(sha256_hex(token)), file: None }
    }

    /// Whether tokens are checked.
    pub fn is_open(&self) -> bool {
        self.single.is_none() && self.file.is_none()
    }

    /// Who sent `metadata`; `robot_hash` gives the stored hash of a robot's token.
    pub fn caller(
        &self,
        metadata: &MetadataMap,
        robot_hash: impl Fn(RobotId) -> Option<String>,
    ) -> Result<Caller, Error> {
        if self.is_open() {
            return Ok(Caller::Anonymous);
        }
        let token = bearer(metadata)?;
        let hash = sha256_hex(token);
        if self.single.as_ref() == Some(&hash) {
            return Ok(Caller::Operator { name: "operator".to_owned(), role: Role::Operator });
        }
        if let Some(file) = &self.file {
            let mut file = file.lock().unwrap_or_else(|e| e.into_inner());
            file.refresh();
            if let Some(holder) = file.holders.get(&hash) {
                return Ok(Caller::Operator { name: holder.name.clone(), role: holder.role });
            }
        }
        if let Some(robot) = robot_of(token)
            && robot_hash(robot).is_some_and(|stored| stored == hash)
        {
            return Ok(Caller::Robot(robot));
        }
        Err(Error::Unauthenticated(
            "the bearer token is not valid: use an operator token or the token RegisterRobot returned \
             (a robot's token changes each time it registers)"
                .to_owned(),
        ))
    }
}

/// The one authentication layer: a tonic interceptor that puts the
/// [`Caller`] into every request's extensions, or refuses the call.
#[derive(Clone)]
pub struct AuthLayer {
    auth: Arc<Authenticator>,
    robot_hash: Arc<dyn Fn(RobotId) -> Option<String> + Send + Sync>,
}

impl std::fmt::Debug for AuthLayer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AuthLayer").field("auth", &self.auth).finish_non_exhaustive()
    }
}

impl AuthLayer {
    /// Checks tokens with `auth`, robot tokens against `robot_hash`.
    pub fn new(auth: Authenticator, robot_hash: impl Fn(RobotId) -> Option<String> + Send + Sync + 'static) -> Self {
        Self { auth: Arc::new(auth), robot_hash: Arc::new(robot_hash) }
    }
}

impl tonic::service::Interceptor for AuthLayer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        let caller = self.auth.caller(request.metadata(), |robot| (self.robot_hash)(robot))?;
        request.extensions_mut().insert(caller);
        Ok(request)
    }
}

fn bearer(metadata: &MetadataMap) -> Result<&str, Error> {
    let missing = || {
        Error::Unauthenticated(
            "this executive requires a bearer token: send `authorization: Bearer <token>` metadata \
             (coordctl --token or COORDINATOR_TOKEN)"
                .to_owned(),
        )
    };
    let value = metadata.get("authorization").ok_or_else(missing)?;
    let value = value.to_str().map_err(|_| missing())?;
    value
        .strip_prefix("Bearer ")
        .or_else(|| value.strip_prefix("bearer "))
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .ok_or_else(missing)
}

fn robot_of(token: &str) -> Option<RobotId> {
    let rest = token.strip_prefix("rbt_")?;
    let (id, secret) = rest.split_once('_')?;
    (secret.len() == 64).then_some(())?;
    id.parse().ok()
}

/// SHA-256 of a token, lower-case hex: what the store keeps.
pub fn sha256_hex(token: &str) -> String {
    Sha256::digest(token.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
}

/// 32 bytes of OS randomness as 64 lower-case hex digits.
fn random_secret() -> Result<String, Error> {
    let mut secret = [0u8; 32];
    getrandom::fill(&mut secret).map_err(|e| Error::Internal(format!("no randomness for a token: {e}")))?;
    Ok(secret.iter().map(|b| format!("{b:02x}")).collect())
}

/// The secret part of a robot token, drawn before the robot's identity is
/// known: the token is `rbt_<robot id>_<secret>`.
#[derive(Clone)]
pub struct RobotSecret(String);

impl std::fmt::Debug for RobotSecret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RobotSecret(..)")
    }
}

impl RobotSecret {
    /// 32 bytes of OS randomness.
    pub fn new() -> Result<Self, Error> {
        Ok(Self(random_secret()?))
    }

    /// The token of `robot`.
    pub fn token(&self, robot: RobotId) -> String {
        format!("rbt_{robot}_{}", self.0)
    }

    /// The hash the store keeps of `robot`'s token.
    pub fn token_hash(&self, robot: RobotId) -> String {
        sha256_hex(&self.token(robot))
    }
}

/// A fresh operator token, for an executive started inside another program
/// (the simulator's loopback executive) that should not run open.
pub fn random_operator_token() -> Result<String, Error> {
    Ok(format!("opr_{}", random_secret()?))
}

/// A fresh token for a viewer (who may only read), told apart from an
/// operator's by its prefix.
pub fn random_viewer_token() -> Result<String, Error> {
    Ok(format!("vwr_{}", random_secret()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metadata(token: Option<&str>) -> MetadataMap {
        let mut m = MetadataMap::new();
        if let Some(t) = token {
            m.insert("authorization", format!("Bearer {t}").parse().unwrap());
        }
        m
    }

    fn operator(name: &str) -> Caller {
        Caller::Operator { name: name.to_owned(), role: Role::Operator }
    }

    #[test]
    fn random_operator_tokens_differ_and_are_not_robot_tokens() {
        let (a, b) = (random_operator_token().unwrap(), random_operator_token().unwrap());
        assert_ne!(a, b);
        assert_eq!(a.len(), 4 + 64);
        assert_eq!(robot_of(&a), None);
        let auth = Authenticator::with_operator_token(&a);
        assert_eq!(auth.caller(&metadata(Some(&a)), |_| None).unwrap(), operator("operator"));
        assert!(auth.caller(&metadata(Some(&b)), |_| None).is_err());
        let viewer = random_viewer_token().unwrap();
        assert!(viewer.starts_with("vwr_") && viewer.len() == 4 + 64 && robot_of(&viewer).is_none());
    }

    #[test]
    fn tokens_identify_operators_and_robots_and_nothing_else() {
        let auth = Authenticator::new(Some("s3cret-s3cret-s3cret"), None).unwrap();
        let secret = RobotSecret::new().unwrap();
        let (robot_token, robot_hash) = (secret.token(7), secret.token_hash(7));
        let other_token = RobotSecret::new().unwrap().token(7);
        assert_ne!(robot_token, other_token, "tokens are random");
        let lookup = |id: RobotId| (id == 7).then(|| robot_hash.clone());
        assert_eq!(auth.caller(&metadata(Some("s3cret-s3cret-s3cret")), lookup).unwrap(), operator("operator"));
        assert_eq!(auth.caller(&metadata(Some(&robot_token)), lookup).unwrap(), Caller::Robot(7));
        for bad in [None, Some("wrong"), Some(other_token.as_str()), Some("rbt_7_00")] {
            let err = auth.caller(&metadata(bad), lookup).unwrap_err();
            assert!(matches!(err, Error::Unauthenticated(_)), "{bad:?}: {err}");
        }
        assert!(Caller::Robot(7).require_robot(7).is_ok());
        assert!(matches!(Caller::Robot(7).require_robot(8), Err(Error::PermissionDenied(_))));
        assert!(matches!(Caller::Robot(7).require_operator("x"), Err(Error::PermissionDenied(_))));
        assert_eq!(Authenticator::open().caller(&metadata(None), lookup).unwrap(), Caller::Anonymous);
        assert_eq!(sha256_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    }

    #[test]
    fn blank_or_short_operator_tokens_refuse_to_start_instead_of_running_open() {
        for blank in ["", "   ", "\t\n"] {
            assert!(matches!(Authenticator::new(Some(blank), None), Err(TokensError::Empty)), "{blank:?}");
        }
        assert!(matches!(Authenticator::new(Some("short"), None), Err(TokensError::Short(5))));
        assert!(Authenticator::new(None, None).unwrap().is_open());
    }

    #[test]
    fn named_tokens_carry_their_name_and_role_and_follow_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tokens");
        let line = |name: &str, role: &str, token: &str| format!("{name} {role} {}\n", sha256_hex(token));
        std::fs::write(
            &path,
            format!(
                "# who may do what\n{}{}",
                line("ana", "operator", "ana-token"),
                line("kim", "viewer", "kim-token")
            ),
        )
        .unwrap();
        let auth = Authenticator::new(None, Some(&path)).unwrap();
        let ana = auth.caller(&metadata(Some("ana-token")), |_| None).unwrap();
        assert_eq!(ana, operator("ana"));
        assert_eq!(ana.actor("someone else"), "ana", "the record names the token, not the claim");
        let kim = auth.caller(&metadata(Some("kim-token")), |_| None).unwrap();
        assert!(kim.require_operator("pausing").is_err());
        assert!(kim.require_robot(3).is_err());
        // Revoked by rewriting the file: refused at the next call, no restart.
        std::fs::write(&path, line("kim", "viewer", "kim-token")).unwrap();
        assert!(matches!(auth.caller(&metadata(Some("ana-token")), |_| None), Err(Error::Unauthenticated(_))));
        assert!(auth.caller(&metadata(Some("kim-token")), |_| None).is_ok());
        // A file broken later admits nobody (fails closed).
        std::fs::write(&path, "kim viewer not-a-hash-at-all\n").unwrap();
        assert!(auth.caller(&metadata(Some("kim-token")), |_| None).is_err());
    }

    #[test]
    fn malformed_token_files_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tokens");
        let hash = sha256_hex("x");
        for (text, needle) in [
            ("ana operator\n".to_owned(), "line 1"),
            (format!("\nana admin {hash}\n"), "line 2: role"),
            ("ana operator abc\n".to_owned(), "SHA-256"),
            (format!("ana operator {hash}\nbob viewer {hash}\n"), "line 2"),
            (format!("a\u{7}na operator {hash}\n"), "control character"),
        ] {
            std::fs::write(&path, &text).unwrap();
            let err = Authenticator::new(None, Some(&path)).unwrap_err().to_string();
            assert!(err.contains(needle), "{text:?}: {err}");
        }
    }
}
