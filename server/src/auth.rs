//! Who is calling: bearer tokens for operators and robots.
//!
//! The operator token is configured on the executive; each robot's token is
//! issued at registration and only its SHA-256 is kept. A robot token reads
//! `rbt_<robot id>_<32 random bytes in hex>`, so that the executive finds the
//! hash to compare with without scanning. Without an operator token the
//! executive runs open: every caller may do everything (loopback and tests).

use sha2::{Digest, Sha256};
use tonic::metadata::MetadataMap;

use crate::domain::RobotId;
use crate::error::Error;

/// Who a request comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Caller {
    /// The operator token, or anyone when the executive runs open.
    Operator,
    /// A robot's own token.
    Robot(RobotId),
}

impl Caller {
    /// Only operators may administer missions and override robots.
    pub fn require_operator(self, what: &str) -> Result<(), Error> {
        match self {
            Self::Operator => Ok(()),
            Self::Robot(id) => Err(Error::PermissionDenied(format!(
                "{what} needs the operator token; the token of robot {id} may only report as that robot and read"
            ))),
        }
    }

    /// A robot may act only as itself; operators as any robot.
    pub fn require_robot(self, robot: RobotId) -> Result<(), Error> {
        match self {
            Self::Operator => Ok(()),
            Self::Robot(id) if id == robot => Ok(()),
            Self::Robot(id) => Err(Error::PermissionDenied(format!(
                "the token of robot {id} may not act as robot {robot}; each robot uses the token its registration returned"
            ))),
        }
    }
}

/// Checks bearer tokens.
#[derive(Debug, Clone, Default)]
pub struct Authenticator {
    operator_sha256: Option<String>,
}

impl Authenticator {
    /// Every caller is an operator: no token is checked.
    pub fn open() -> Self {
        Self { operator_sha256: None }
    }

    /// Requires `token` for operator calls and robot tokens for robots.
    pub fn with_operator_token(token: &str) -> Self {
        Self { operator_sha256: Some(sha256_hex(token)) }
    }

    /// Whether tokens are checked.
    pub fn is_open(&self) -> bool {
        self.operator_sha256.is_none()
    }

    /// Who sent `metadata`; `robot_hash` gives the stored hash of a robot's token.
    pub fn caller(
        &self,
        metadata: &MetadataMap,
        robot_hash: impl Fn(RobotId) -> Option<String>,
    ) -> Result<Caller, Error> {
        let Some(operator) = &self.operator_sha256 else { return Ok(Caller::Operator) };
        let token = bearer(metadata)?;
        let hash = sha256_hex(token);
        if &hash == operator {
            return Ok(Caller::Operator);
        }
        if let Some(robot) = robot_of(token)
            && robot_hash(robot).is_some_and(|stored| stored == hash)
        {
            return Ok(Caller::Robot(robot));
        }
        Err(Error::Unauthenticated(
            "the bearer token is not valid: use the operator token or the token RegisterRobot returned \
             (a robot's token changes each time it registers)"
                .to_owned(),
        ))
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

/// A new token for a robot and its hash.
pub fn issue_robot_token(robot: RobotId) -> Result<(String, String), Error> {
    let token = format!("rbt_{robot}_{}", random_secret()?);
    let hash = sha256_hex(&token);
    Ok((token, hash))
}

/// A fresh operator token, for an executive started inside another program
/// (the simulator's loopback executive) that should not run open.
pub fn random_operator_token() -> Result<String, Error> {
    Ok(format!("opr_{}", random_secret()?))
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

    #[test]
    fn random_operator_tokens_differ_and_are_not_robot_tokens() {
        let (a, b) = (random_operator_token().unwrap(), random_operator_token().unwrap());
        assert_ne!(a, b);
        assert_eq!(a.len(), 4 + 64);
        assert_eq!(robot_of(&a), None);
        let auth = Authenticator::with_operator_token(&a);
        assert_eq!(auth.caller(&metadata(Some(&a)), |_| None).unwrap(), Caller::Operator);
        assert!(auth.caller(&metadata(Some(&b)), |_| None).is_err());
    }

    #[test]
    fn tokens_identify_operators_and_robots_and_nothing_else() {
        let auth = Authenticator::with_operator_token("s3cret");
        let (robot_token, robot_hash) = issue_robot_token(7).unwrap();
        let (other_token, _) = issue_robot_token(7).unwrap();
        assert_ne!(robot_token, other_token, "tokens are random");
        let lookup = |id: RobotId| (id == 7).then(|| robot_hash.clone());
        assert_eq!(auth.caller(&metadata(Some("s3cret")), lookup).unwrap(), Caller::Operator);
        assert_eq!(auth.caller(&metadata(Some(&robot_token)), lookup).unwrap(), Caller::Robot(7));
        for bad in [None, Some("wrong"), Some(other_token.as_str()), Some("rbt_7_00")] {
            let err = auth.caller(&metadata(bad), lookup).unwrap_err();
            assert!(matches!(err, Error::Unauthenticated(_)), "{bad:?}: {err}");
        }
        assert!(Caller::Robot(7).require_robot(7).is_ok());
        assert!(matches!(Caller::Robot(7).require_robot(8), Err(Error::PermissionDenied(_))));
        assert!(matches!(Caller::Robot(7).require_operator("x"), Err(Error::PermissionDenied(_))));
        assert_eq!(Authenticator::open().caller(&metadata(None), lookup).unwrap(), Caller::Operator);
        assert_eq!(sha256_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    }
}
