//! The C allocator's arenas (glibc): how much freed memory a holon process keeps.
//!
//! glibc gives a thread that allocates while the other arenas are busy an arena of its
//! own, up to 8 per core, and keeps every arena for the life of the process with the
//! free memory it held at its high-water mark. A holon process makes many short-lived
//! threads: every journal write that may block ([`crate::journal::blocking`]) hands its
//! runtime thread over to a new one, so an order-node with a few dozen orders writing at
//! once runs 40-50 threads, and soon has 16 arenas (two cores), each keeping what it
//! once held. Measured (a debug order-node, waves of 40 orders every 5 s for 4
//! minutes, 1,920 orders, then idle; glibc's own counters): 23.6 MB held by the
//! allocator of which 5.4 MB in use, anonymous memory 25.3 MB. With two arenas: 15.3 MB
//! held (5.3 MB in use), anonymous memory 17.5 MB. What is in use still grows about
//! 1 KB per finished order: zenoh's routing tables keep every order token's key
//! (docs/reliability.md, "Memory while running").

/// The most arenas a holon process uses: the `MALLOC_ARENA_MAX` environment variable
/// (glibc's own knob) when set, else this many.
pub const ARENAS: i32 = 2;

/// Limits the allocator's arenas to [`ARENAS`] unless the user set `MALLOC_ARENA_MAX`.
/// For a binary's `main`, before any thread is started. Does nothing off glibc.
pub fn limit_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        // SAFETY: mallopt only sets an allocator parameter; called before other threads.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, ARENAS);
        }
    }
}
