//! The users file: round trip, refusals, verification, concurrent changes.

use std::os::unix::fs::PermissionsExt;

use super::*;

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

#[test]
fn roles_are_ordered_and_parsed() {
    assert!(Role::Observer < Role::Operator && Role::Operator < Role::Admin);
    assert!(!Role::Observer.may_operate());
    assert!(Role::Operator.may_operate() && Role::Admin.may_operate());
    assert!(Role::Admin.may_manage_users() && !Role::Operator.may_manage_users());
    for role in [Role::Observer, Role::Operator, Role::Admin] {
        assert_eq!(role.as_str().parse::<Role>().unwrap(), role);
    }
    assert!("root"
        .parse::<Role>()
        .unwrap_err()
        .to_string()
        .contains("observer, operator or admin"));
}

#[test]
fn a_changed_file_reads_back_the_same_and_is_its_owners_alone() {
    let dir = tempfile::tempdir().unwrap();
    let path = default_path(dir.path());
    assert_eq!(path, dir.path().join("users.toml"));
    change(&path, |users| {
        users.add("anna", Role::Operator, "anna-password")?;
        users.add("root.admin", Role::Admin, "admin-password")?;
        users.add("wall_1", Role::Observer, "wall-password")
    })
    .unwrap();
    assert_eq!(mode(&path), 0o600);
    assert_eq!(mode(&dir.path().join("users.toml.lock")), 0o600);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(!text.contains("anna-password"), "{text}");
    assert!(text.contains("$argon2id$v=19$m=19456,t=2,p=1$"), "{text}");
    let users = load(&path).unwrap();
    let names: Vec<(&str, Role)> = users.iter().map(|u| (u.name.as_str(), u.role)).collect();
    assert_eq!(
        names,
        [
            ("anna", Role::Operator),
            ("root.admin", Role::Admin),
            ("wall_1", Role::Observer)
        ]
    );
    // Changed again: read, changed, written whole; the rest as before.
    let before = users.get("wall_1").unwrap().password.clone();
    change(&path, |users| {
        users.set_password("anna", "another-password")
    })
    .unwrap();
    let users = load(&path).unwrap();
    assert_eq!(users.get("wall_1").unwrap().password, before);
    assert!(users.verify("anna", "another-password").is_some());
    assert!(users.verify("anna", "anna-password").is_none());
    // No `{:?}` shows a hash.
    assert!(!format!("{users:?}").contains("argon2"));
    // No temporary file is left.
    let mut left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["users.toml", "users.toml.lock"]);
}

#[test]
fn verify_knows_the_right_password_only() {
    let mut users = Users::default();
    users.add("anna", Role::Operator, "anna-password").unwrap();
    assert_eq!(
        users.verify("anna", "anna-password").unwrap().role,
        Role::Operator
    );
    assert!(users.verify("anna", "anna-passwore").is_none());
    assert!(users.verify("anna", "").is_none());
    assert!(users.verify("bert", "anna-password").is_none());
    // An unknown name takes about as long as a wrong password (a hash is verified);
    // the fastest of three, as other tests share the cores.
    let time = |name: &str| {
        (0..3)
            .map(|_| {
                let start = std::time::Instant::now();
                assert!(users.verify(name, "wrong-password").is_none());
                start.elapsed()
            })
            .min()
            .unwrap()
    };
    let (known, unknown) = (time("anna"), time("nobody"));
    assert!(
        unknown * 3 > known && known * 3 > unknown,
        "wrong password {known:?}, unknown user {unknown:?}"
    );
}

#[test]
fn bad_changes_are_refused() {
    let mut users = Users::default();
    for bad in ["", "anna smith", "änna", "a/b", &"x".repeat(65)] {
        assert!(
            matches!(
                users.add(bad, Role::Operator, "long-enough"),
                Err(UsersError::BadName(_))
            ),
            "{bad:?}"
        );
    }
    users
        .add(&"x".repeat(64), Role::Operator, "long-enough")
        .unwrap();
    assert!(matches!(
        users.add("anna", Role::Operator, "short"),
        Err(UsersError::ShortPassword)
    ));
    users.add("anna", Role::Operator, "long-enough").unwrap();
    assert!(matches!(
        users.add("anna", Role::Admin, "long-enough"),
        Err(UsersError::Exists(_))
    ));
    assert!(matches!(
        users.set_password("anna", "1234567"),
        Err(UsersError::ShortPassword)
    ));
    assert!(matches!(
        users.set_password("bert", "long-enough"),
        Err(UsersError::Unknown(_))
    ));
    assert!(matches!(users.remove("bert"), Err(UsersError::Unknown(_))));
    // No admin at all is allowed: operators change roles and leave freely.
    assert_eq!(
        users.set_role("anna", Role::Observer).unwrap(),
        Role::Operator
    );
    users.remove(&"x".repeat(64)).unwrap();
    // Once there is an admin, the last one stays.
    users.add("root", Role::Admin, "long-enough").unwrap();
    let last = users.remove("root").unwrap_err();
    assert!(
        last.to_string().contains("add another admin first"),
        "{last}"
    );
    assert!(matches!(
        users.set_role("root", Role::Operator),
        Err(UsersError::LastAdmin(_))
    ));
    users.set_role("anna", Role::Admin).unwrap();
    users.set_role("root", Role::Operator).unwrap();
    assert!(matches!(
        users.remove("anna"),
        Err(UsersError::LastAdmin(_))
    ));
    users.set_role("anna", Role::Admin).unwrap();
}

#[test]
fn a_refused_change_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("users.toml");
    change(&path, |users| {
        users.add("anna", Role::Admin, "anna-password")
    })
    .unwrap();
    let before = std::fs::read(&path).unwrap();
    assert!(matches!(
        change(&path, |users| users.remove("anna")),
        Err(UsersError::LastAdmin(_))
    ));
    assert_eq!(std::fs::read(&path).unwrap(), before);
}

#[test]
fn a_bad_file_is_refused_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("users.toml");
    let write = |text: &str| {
        std::fs::write(&path, text).unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
    };
    let hash = password::hash("anna-password");
    let good = format!("[[user]]\nname = \"anna\"\nrole = \"operator\"\npassword = \"{hash}\"\n");
    write(&good);
    assert_eq!(load(&path).unwrap().len(), 1);
    // Open to others: refused, naming the fix; so is changing it.
    for open in [0o644, 0o660, 0o602] {
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(open)).unwrap();
        let refused = load(&path).unwrap_err().to_string();
        assert!(
            refused.contains(&format!("chmod 600 {}", path.display())),
            "{refused}"
        );
        assert!(change(&path, |_| Ok(())).is_err());
    }
    let refused = |text: &str| {
        write(text);
        load(&path).unwrap_err().to_string()
    };
    let said = refused(&format!(
        "{good}[[user]]\nname = \"anna\"\nrole = \"observer\"\npassword = \"{hash}\"\n"
    ));
    assert!(said.contains("user anna appears twice"), "{said}");
    let said = refused(&good.replace("operator", "root"));
    assert!(said.contains("line 3"), "{said}");
    let said = refused(&format!("{good}email = \"a@b\"\n"));
    assert!(said.contains("email"), "{said}");
    let said = refused(&good.replace(&hash, "pbkdf2-sha256$100000$00$00"));
    assert!(
        said.contains("user anna") && !said.contains("pbkdf2-sha256$"),
        "{said}"
    );
    let said = refused(&good.replace("\"anna\"", "\"an na\""));
    assert!(said.contains("bad user name"), "{said}");
    // Missing: an error from load, an empty file for change.
    std::fs::remove_file(&path).unwrap();
    assert!(matches!(load(&path), Err(UsersError::Read { .. })));
    assert!(change(&path, |users| Ok(users.is_empty())).unwrap());
}

#[test]
fn two_changes_at_once_keep_both() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("users.toml");
    let barrier = std::sync::Barrier::new(2);
    std::thread::scope(|s| {
        for name in ["anna", "bert"] {
            let (path, barrier) = (&path, &barrier);
            s.spawn(move || {
                barrier.wait();
                change(path, |users| users.add(name, Role::Operator, "long-enough")).unwrap();
            });
        }
    });
    let users = load(&path).unwrap();
    assert!(
        users.get("anna").is_some() && users.get("bert").is_some(),
        "{users:?}"
    );
}
