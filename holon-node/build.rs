//! Links the `holon-node` binary with the functions a resource holon runs placed
//! together, in the order it first runs them (`link-order.txt`, made by
//! `link-order.sh`; docs/benchmarks.md, "Code in the order it runs"). The kernel maps
//! 64 KiB of the binary around each page fault of its code, so a holon whose code is
//! spread over the whole text has most of the text resident; gathered, it has little.
//!
//! Only for release builds (the file's names are those of the release build's symbols),
//! and only where the linker is rustc's own `rust-lld` (the default on
//! x86_64-unknown-linux-gnu since Rust 1.90): no linker, `-C linker` or linker flag set
//! in the build's flags. `HOLARCHY_LINK_ORDER=off` leaves it out. Names the file holds
//! that the build does not have (code changed since the file was made) are skipped
//! silently: the order is only a layout, never a difference in what the binary does.
//! Changing the file builds this crate again (its binary is linked anew), nothing else.

use std::env;
use std::path::PathBuf;
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=link-order.txt");
    println!("cargo:rerun-if-env-changed=HOLARCHY_LINK_ORDER");
    if env::var("PROFILE").as_deref() != Ok("release") {
        // Debug builds (every test build): not the layout the file was made from, and
        // nothing to gain.
        return;
    }
    if let Some(why) = not_applied() {
        println!("cargo:warning=holon-node: link order not applied ({why})");
        return;
    }
    let file = PathBuf::from(env::var("CARGO_MANIFEST_DIR").unwrap()).join("link-order.txt");
    println!(
        "cargo:rustc-link-arg-bins=-Wl,--symbol-ordering-file={}",
        file.display()
    );
    println!("cargo:rustc-link-arg-bins=-Wl,--no-warn-symbol-ordering");
}

/// Why the ordering file is not passed to the linker, or `None` when it is.
fn not_applied() -> Option<String> {
    let var = |name: &str| env::var(name).unwrap_or_default();
    if var("HOLARCHY_LINK_ORDER") == "off" {
        return Some("HOLARCHY_LINK_ORDER=off".into());
    }
    if var("TARGET") != "x86_64-unknown-linux-gnu" {
        return Some(format!(
            "target {}, not x86_64-unknown-linux-gnu",
            var("TARGET")
        ));
    }
    if env::var_os("RUSTC_LINKER").is_some() {
        return Some("a linker is configured".into());
    }
    let flags = var("CARGO_ENCODED_RUSTFLAGS");
    if flags.contains("linker") || flags.contains("fuse-ld") {
        return Some("the build's flags choose the linker".into());
    }
    // rustc links with its own lld on this target since 1.90.
    let rustc = env::var_os("RUSTC").unwrap_or_else(|| "rustc".into());
    let version = Command::new(rustc)
        .arg("--version")
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
        .unwrap_or_default();
    let minor = version
        .split_whitespace()
        .nth(1)
        .and_then(|v| v.split('.').nth(1))
        .and_then(|m| m.parse::<u32>().ok());
    match minor {
        Some(m) if m >= 90 => None,
        _ => Some(format!("{} links with the system's linker", version.trim())),
    }
}
