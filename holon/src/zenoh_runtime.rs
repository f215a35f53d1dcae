//! The thread pools zenoh runs its own work on, as the holon processes set them.
//!
//! Zenoh keeps five tokio runtimes of its own beside the process's: `app` (callbacks,
//! one thread), `acc` (accepting links, one), `tx` (writing batches, one), `rx` (reading
//! links, two) and `net` (one). A holon's service round trip crosses several of them:
//! a query is read on an `rx` thread, its reply written by the `tx` thread, and on a
//! virtual machine waking an idle thread is what such a round trip mostly waits on.
//! A holon process hands `rx`, `tx`, `acc` and `net` over to `app`, which gets two
//! threads: the same work on two threads instead of six, each more often already awake.
//! Measured beside zenoh's default on the same machine (docs/benchmarks.md, "zenoh's
//! runtimes in one pool"): the zenoh round trip about 20% shorter, the service cycle 12-15%.
//!
//! The holon's own tasks run on the same pool ([`runtime`]): a zenoh callback runs on one
//! of its threads, and the task it hands a request to (a component's mailbox) then runs
//! on that thread right after it, where a runtime of the process's own had to wake one
//! of its threads first (27 us of the 66 a booking spent inside the resource; measured
//! in docs/benchmarks.md, "One pool for zenoh and the holon"). Two threads whatever
//! the host's cores: a holon handles a few messages at a time. An order-node hosting
//! thousands of orders on a large host may want more (`(app: (worker_threads: 8), ...)`).
//!
//! The `ZENOH_RUNTIME` environment variable is zenoh's own knob
//! (<https://docs.rs/zenoh-runtime>, RON, e.g. `(app: (worker_threads: 4))`): when it is
//! set, it is used as it is and nothing here changes it.

/// The holon processes' setting: every zenoh runtime handed over to `app`, two threads,
/// and as many blocking threads as tokio's own default (512; zenoh's default is 50). The
/// journals' calls that may block hand their thread's work to a new one while they
/// wait (`holon::journal::blocking`): an order-node whose hundred orders write to etcd
/// at once needs a hundred, and with fewer it stopped, every thread waiting on an etcd
/// call that no thread was left to drive.
pub const HOLON_ZENOH_RUNTIME: &str = "(rx: (handover: app), tx: (handover: app), \
     acc: (handover: app), net: (handover: app), \
     app: (worker_threads: 2, max_blocking_threads: 512))";

/// zenoh's environment variable for its runtimes.
pub const ZENOH_RUNTIME_ENV: &str = "ZENOH_RUNTIME";

/// Sets [`HOLON_ZENOH_RUNTIME`] unless `ZENOH_RUNTIME` is set already. For a binary's
/// `main`, before any thread is started (it writes the process environment, which
/// another thread may be reading) and before zenoh is first used (zenoh reads it once).
/// The processes this one starts inherit it.
pub fn configure() {
    if std::env::var_os(ZENOH_RUNTIME_ENV).is_none() {
        std::env::set_var(ZENOH_RUNTIME_ENV, HOLON_ZENOH_RUNTIME);
    }
}

/// The runtime a holon process runs on: zenoh's `app` pool (see the module). Made by
/// zenoh at first use, with `ZENOH_RUNTIME`'s setting: call [`configure`] first.
pub fn runtime() -> tokio::runtime::Handle {
    use std::ops::Deref;
    ::zenoh_runtime::ZRuntime::Application.deref().clone()
}
