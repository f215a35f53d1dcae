//! Password hashes: argon2id PHC strings (`$argon2id$v=19$m=19456,t=2,p=1$<salt>$<hash>`)
//! with OWASP's parameters (the `argon2` crate's defaults: 19 MiB, 2 passes, 1 lane).
//!
//! Hashing or verifying costs tens of milliseconds of one core and 19 MiB: callers in
//! async code run it in `tokio::task::spawn_blocking`. A server that verifies many
//! passwords does so into memory it keeps ([`Memory`], [`verify_in`]): 19 MiB
//! allocated and freed per login is kept by the C allocator in every thread's arena
//! (measured: 8 parallel guessers took a `cell` process from 117 MB to 566 MB).

use argon2::password_hash::rand_core::OsRng;
use argon2::password_hash::{PasswordHash, PasswordHasher, SaltString};
use argon2::{Algorithm, Argon2, Block, Params};

/// The shortest password accepted for a new or changed password, in characters.
pub const MIN_LENGTH: usize = 8;

/// The hash verified when a login names no known user, so that the time a refusal
/// takes does not tell which names exist (a valid hash with the default parameters
/// whose password no one knows).
const DUMMY: &str = "$argon2id$v=19$m=19456,t=2,p=1$bm9ib2R5LWlzLWhlcmU$+Dl4u8xpF0SO1oX2Q0nBpy0fzZT2jtQUKTo2sBaiv1E";

/// Hashes `password` with a new random salt: a PHC string.
pub fn hash(password: &str) -> String {
    let salt = SaltString::generate(&mut OsRng);
    Argon2::default()
        .hash_password(password.as_bytes(), &salt)
        .expect("argon2 with its default parameters hashes any password")
        .to_string()
}

/// Whether `phc` is an argon2id PHC string this module can verify against; the error
/// says what is wrong (never the string itself).
pub fn check(phc: &str) -> Result<(), String> {
    let parsed = PasswordHash::new(phc).map_err(|e| {
        format!("the password is not a PHC string ({e}); `cell users passwd` writes one")
    })?;
    if parsed.algorithm != Algorithm::Argon2id.ident() {
        return Err(format!(
            "the password hash is {}, not argon2id; `cell users passwd` writes one",
            parsed.algorithm
        ));
    }
    if parsed.hash.is_none() || parsed.salt.is_none() {
        return Err("the password hash has no salt or no hash".into());
    }
    argon2::Params::try_from(&parsed)
        .map_err(|e| format!("the password hash's parameters are not valid: {e}"))?;
    Ok(())
}

/// Whether `password` is the one hashed in `phc` (constant time in the hash; false for
/// a string that is not a valid hash), in working memory of its own ([`verify_in`]).
pub fn verify(phc: &str, password: &str) -> bool {
    verify_in(phc, password, &mut Memory::default())
}

/// Spends the time of a verification against nothing (an unknown user's login).
pub fn verify_dummy(password: &str) {
    verify_dummy_in(password, &mut Memory::default());
}

/// The working memory of one verification, kept from one to the next.
#[derive(Default)]
pub struct Memory(Vec<Block>);

impl std::fmt::Debug for Memory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Memory({} KiB)", self.0.len())
    }
}

/// [`verify`], in `memory` (grown to the hash's memory cost, and kept).
pub fn verify_in(phc: &str, password: &str, memory: &mut Memory) -> bool {
    let Ok(parsed) = PasswordHash::new(phc) else {
        return false;
    };
    let (Ok(algorithm), Some(salt), Some(expected)) = (
        Algorithm::try_from(parsed.algorithm),
        parsed.salt,
        parsed.hash,
    ) else {
        return false;
    };
    let version = match parsed.version.map(argon2::Version::try_from).transpose() {
        Ok(version) => version.unwrap_or_default(),
        Err(_) => return false,
    };
    let Ok(params) = Params::try_from(&parsed) else {
        return false;
    };
    let mut salt_bytes = [0u8; 64];
    let Ok(salt) = salt.decode_b64(&mut salt_bytes) else {
        return false;
    };
    let blocks = params.block_count();
    if memory.0.len() < blocks {
        memory.0.resize(blocks, Block::default());
    }
    let mut out = vec![0u8; expected.len()];
    let hashed = Argon2::new(algorithm, version, params).hash_password_into_with_memory(
        password.as_bytes(),
        salt,
        &mut out,
        &mut memory.0[..blocks],
    );
    // `Output`'s comparison is constant-time.
    hashed.is_ok() && argon2::password_hash::Output::new(&out).is_ok_and(|out| out == expected)
}

/// [`verify_dummy`], in `memory`.
pub fn verify_dummy_in(password: &str, memory: &mut Memory) {
    let _ = verify_in(DUMMY, password, memory);
}

/// Whether `password` is long enough for a new password ([`MIN_LENGTH`]).
pub fn long_enough(password: &str) -> bool {
    password.chars().count() >= MIN_LENGTH
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hash_verifies_its_password_only() {
        let phc = hash("correct horse");
        assert!(phc.starts_with("$argon2id$v=19$m=19456,t=2,p=1$"), "{phc}");
        check(&phc).unwrap();
        assert!(verify(&phc, "correct horse"));
        assert!(!verify(&phc, "correct horse "));
        assert!(!verify(&phc, ""));
        assert_ne!(hash("correct horse"), phc, "a new salt every time");
        assert!(check("pbkdf2-sha256$100000$00$00").is_err());
        assert!(check("$argon2i$v=19$m=19456,t=2,p=1$bm9ib2R5LWlzLWhlcmU$+Dl4u8xpF0SO1oX2Q0nBpy0fzZT2jtQUKTo2sBaiv1E").is_err());
        assert!(!verify("nonsense", "correct horse"));
        let mut memory = Memory::default();
        assert!(verify_in(&phc, "correct horse", &mut memory));
        assert!(!verify_in(&phc, "correct horse ", &mut memory));
        assert!(!verify_in("nonsense", "correct horse", &mut memory));
        assert!(!verify_in(DUMMY, "correct horse", &mut memory));
        assert_eq!(memory.0.len(), 19456, "19 MiB, kept");
    }

    #[test]
    fn the_dummy_hash_costs_what_a_real_one_does() {
        check(DUMMY).unwrap();
        let dummy = PasswordHash::new(DUMMY).unwrap();
        let real = hash("whatever1");
        let real = PasswordHash::new(&real).unwrap();
        assert_eq!(dummy.params, real.params);
        assert_eq!(dummy.version, real.version);
    }
}
