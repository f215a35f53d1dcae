//! Where the binaries, the workspace and the demo's configs are, and the log level
//! the children run with.

use std::path::PathBuf;
use std::process::Command;
use std::sync::OnceLock;

/// The directory holding the workspace's binaries (`target/debug` next to the tests,
/// or `HOLARCHY_BIN_DIR`). Absolute: a child started in another directory (the bench
/// starts `cell up` in its copy of a cell) finds them too, where a relative
/// `HOLARCHY_BIN_DIR` would no longer resolve.
pub fn bin_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("HOLARCHY_BIN_DIR") {
        let dir = PathBuf::from(dir);
        return std::path::absolute(&dir).unwrap_or(dir);
    }
    let exe = std::env::current_exe().expect("current exe");
    // A test: target/<profile>/deps/<test>; a binary (bench): target/<profile>/<bin>.
    let dir = exe.parent().expect("the executable has a directory");
    if dir.ends_with("deps") {
        dir.parent().expect("target/<profile>").to_path_buf()
    } else {
        dir.to_path_buf()
    }
}

/// The path of a workspace binary, built on first use if `cargo test` did not build it
/// (the binaries of `HOLARCHY_BIN_DIR` are taken as they are).
pub fn bin(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    let path = bin_dir().join(name);
    BUILT.get_or_init(|| {
        if std::env::var_os("HOLARCHY_BIN_DIR").is_some() {
            return;
        }
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut build = Command::new(cargo);
        build.args(["build", "--bins", "--quiet"]);
        // What cargo sets for a test process is not the user's build environment: a
        // build script that watches one of these (ring's watches CARGO_MANIFEST_DIR)
        // would rebuild half the workspace here, and again at the next plain build.
        for (key, _) in std::env::vars_os() {
            let key = key.to_string_lossy().into_owned();
            if [
                "CARGO_MANIFEST_",
                "CARGO_PKG_",
                "CARGO_CRATE_",
                "CARGO_BIN_",
                "CARGO_PRIMARY_PACKAGE",
                "CARGO_TARGET_TMPDIR",
            ]
            .iter()
            .any(|prefix| key.starts_with(prefix))
            {
                build.env_remove(key);
            }
        }
        // The profile of this executable's directory: target/debug, target/release,
        // target/release-small...
        match bin_dir().file_name().and_then(|n| n.to_str()) {
            Some("debug") | None => {}
            Some(profile) => {
                build.args(["--profile", profile]);
            }
        }
        let status = build
            .current_dir(workspace_root())
            .status()
            .expect("cannot run cargo build");
        assert!(status.success(), "cargo build --bins failed");
    });
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// The workspace's root directory.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is in the workspace")
        .to_path_buf()
}

/// The log level of the holons the harness starts: `HOLARCHY_HOLON_LOG`, default `info`
/// (the tests read the logs; the benchmarks also measure with `warn`).
pub fn holon_log_level() -> String {
    std::env::var("HOLARCHY_HOLON_LOG").unwrap_or_else(|_| "info".into())
}

/// A config shipped in `deploy/cells/demo/`.
pub fn demo_config(file: &str) -> PathBuf {
    workspace_root().join("deploy/cells/demo").join(file)
}

/// The demo's breaker as it was before parts moved (transport a step of its own): for
/// tests that run the demo's holons on a robot-sim each, without a plant.
pub fn stationary_breaker() -> PathBuf {
    workspace_root().join("tests/fixtures/breaker-stationary.toml")
}
