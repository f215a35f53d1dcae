//! The thread pools zenoh runs its own work on, as the holon processes set them.
//!
//! Zenoh keeps five tokio runtimes of its own beside the process's: `app` (callbacks,
//! one thread), `acc` (accepting links, one), `tx` (writing batches, one), `rx` (reading
//! links, two) and `net` (one). A holon's service round trip crosses several of them:
//! a query is read on an `rx` thread, its reply written by the `tx` thread, and on a
//! virtual machine waking an idle thread is what such a round trip mostly waits on.
//! A holon process hands `rx`, `acc` and `net` over to `app`: the same work on one
//! pool instead of five threads, each more often already awake. Measured beside
//! zenoh's default on the same machine (docs/benchmarks.md, "zenoh's runtimes in one
//! pool"): the zenoh round trip about 20% shorter, the service cycle 12-15%.
//!
//! `tx` keeps its one thread. A reply, a publication or a token sent while the link's
//! queue is full does not yield: zenoh blocks the sending thread until `tx` has written
//! a batch out (for at most 5 s, then it closes the link: "Unable to push non
//! droppable network message ... Closing transport!"). With `tx` handed to `app`, a
//! pool whose every thread was so blocked had nobody left to drain the queue: an
//! order-node answering a listing of 1,500 orders while its orders booked lost its link
//! to the router every 5 s (docs/benchmarks.md, "The link's writer keeps its thread";
//! `tests/tests/order_node_load.rs` reproduces it). With a thread of its own, `tx`
//! always runs, and the keep-alives it sends with it.
//!
//! The holon's own tasks run on the same pool ([`runtime`]): a zenoh callback runs on one
//! of its threads, and the task it hands a request to (a component's mailbox) then runs
//! on that thread right after it, where a runtime of the process's own had to wake one
//! of its threads first (27 us of the 66 a booking spent inside the resource; measured
//! in docs/benchmarks.md, "One pool for zenoh and the holon").
//!
//! How many threads ([`Pool`]):
//! - a `holon-node` (a resource, product or staff holon) has **one**: it handles one
//!   message at a time (each holon's state has one owner task), and with a second thread
//!   idle, tokio woke it for every task a message woke, so that the request, the journal
//!   write and the reply each waited on a thread switch (docs/benchmarks.md, "One thread
//!   for a holon-node": a booking 25 us shorter). Work that may block hands the thread
//!   over while it waits ([`crate::journal::blocking`]: an fsync, a file lock), so the
//!   link's keep-alives and the other components go on meanwhile;
//! - an `order-node` has **two**: it hosts many orders at once, each its own task, and
//!   its etcd lease's keep-alives must not wait behind them.
//!
//! An order-node hosting thousands of orders on a large host may want more
//! (`(app: (worker_threads: 8), ...)`). The `ZENOH_RUNTIME` environment variable is
//! zenoh's own knob (<https://docs.rs/zenoh-runtime>, RON, e.g.
//! `(app: (worker_threads: 4))`): when the user set it, it is used as it is and nothing
//! here changes it. The value a holarchy process set for itself (and its children
//! inherit) is not the user's: a child sets its own.

/// The thread pool of a kind of holon process (see the module).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pool {
    /// One thread: a `holon-node` (resource, product, staff).
    Holon,
    /// Two threads: an `order-node`.
    OrderNode,
}

impl Pool {
    /// The pool's worker threads.
    pub fn worker_threads(self) -> usize {
        match self {
            Pool::Holon => 1,
            Pool::OrderNode => 2,
        }
    }

    /// The `ZENOH_RUNTIME` setting: `rx`, `acc` and `net` handed over to `app` (`tx`
    /// keeps its own thread, see the module), `app` with
    /// [`worker_threads`](Self::worker_threads), and as many blocking threads as tokio's
    /// own default (512; zenoh's default is 50). The journals' calls that may block hand
    /// their thread's work to a new one while they wait ([`crate::journal::blocking`]):
    /// an order-node whose hundred orders write to etcd at once needs a hundred, and with
    /// fewer it stopped, every thread waiting on an etcd call that no thread was left to
    /// drive.
    pub fn setting(self) -> String {
        format!(
            "(rx: (handover: app), acc: (handover: app), net: (handover: app), \
             app: (worker_threads: {}, max_blocking_threads: 512))",
            self.worker_threads()
        )
    }
}

/// zenoh's environment variable for its runtimes.
pub const ZENOH_RUNTIME_ENV: &str = "ZENOH_RUNTIME";

/// Where a holarchy process records the `ZENOH_RUNTIME` it set itself: a child that
/// inherits both knows the value is not the user's.
pub const SET_BY_HOLARCHY_ENV: &str = "HOLARCHY_ZENOH_RUNTIME_SET";

/// Sets `pool`'s [`setting`](Pool::setting) unless the user set `ZENOH_RUNTIME`. For a
/// binary's `main`, before any thread is started (it writes the process environment,
/// which another thread may be reading) and before zenoh is first used (zenoh reads it
/// once).
pub fn configure(pool: Pool) {
    let set_by_holarchy = std::env::var_os(SET_BY_HOLARCHY_ENV);
    let set_by_the_user = std::env::var_os(ZENOH_RUNTIME_ENV)
        .is_some_and(|value| Some(&value) != set_by_holarchy.as_ref());
    if !set_by_the_user {
        let setting = pool.setting();
        std::env::set_var(ZENOH_RUNTIME_ENV, &setting);
        std::env::set_var(SET_BY_HOLARCHY_ENV, &setting);
    }
}

/// The runtime a holon process runs on: zenoh's `app` pool (see the module). Made by
/// zenoh at first use, with `ZENOH_RUNTIME`'s setting: call [`configure`] first.
pub fn runtime() -> tokio::runtime::Handle {
    use std::ops::Deref;
    ::zenoh_runtime::ZRuntime::Application.deref().clone()
}
