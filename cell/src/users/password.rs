//! Password hashes: argon2id PHC strings (`$argon2id$v=19$m=19456,t=2,p=1$<salt>$<hash>`)
//! with OWASP's parameters (the `argon2` crate's defaults: 19 MiB, 2 passes, 1 lane).
//!
//! Hashing or verifying costs tens of milliseconds of one core and 19 MiB: callers in
//! async code run it in `tokio::task::spawn_blocking`.

use argon2::password_hash::rand_core::OsRng;
use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use argon2::{Algorithm, Argon2};

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
/// a string that is not a valid hash).
pub fn verify(phc: &str, password: &str) -> bool {
    match PasswordHash::new(phc) {
        Ok(parsed) => Argon2::default()
            .verify_password(password.as_bytes(), &parsed)
            .is_ok(),
        Err(_) => false,
    }
}

/// Spends the time of a verification against nothing (an unknown user's login).
pub fn verify_dummy(password: &str) {
    let _ = verify(DUMMY, password);
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
