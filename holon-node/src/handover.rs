//! What outlives a component's restart: its mailbox and its state.
//!
//! A component owns its state and drains its mailbox; when it crashes, its supervisor
//! starts a successor, which takes both over where it left them. Both are held here,
//! beside the supervisor, behind a lock that the running component holds for its whole
//! life: there is one owner at a time, and nobody else reads or changes what it owns
//! (others see what it publishes, see [`crate::views`]).

use std::sync::Arc;

use tokio::sync::{mpsc, Mutex, OwnedMutexGuard};

/// How many messages a mailbox holds before its senders wait.
pub const MAILBOX: usize = 256;

/// A component's state, taken by the running component and handed to its successor.
///
/// A component that panics leaves a complete state behind: the state machines change
/// their state only in `handle`, which does no I/O and cannot await.
pub struct Handover<T> {
    /// The state. A lock is the right tool here, as a baton, not as shared data: the
    /// running component holds its owned guard for its whole life and nobody else
    /// locks it, so it is never contended while a component runs; the guard gives the
    /// state back when its holder ends, however it ends (a panic's unwinding
    /// included), and a successor's [`take`](Handover::take) waits for exactly that.
    /// A channel would need the same guard, written by hand.
    state: Arc<Mutex<T>>,
}

impl<T> Handover<T> {
    pub fn new(state: T) -> Handover<T> {
        Handover {
            state: Arc::new(Mutex::new(state)),
        }
    }

    /// Another handle on the same state (for the component's links).
    pub fn share(&self) -> Handover<T> {
        Handover {
            state: self.state.clone(),
        }
    }

    /// Takes the state for the caller's life (waits while a predecessor still runs).
    pub async fn take(&self) -> OwnedMutexGuard<T> {
        self.state.clone().lock_owned().await
    }
}

/// A component's mailbox: the sender is cloned freely; the receiver is held by the
/// running component and taken over by its successor, so no message is lost to a
/// restart. Bounded: a sender waits while the mailbox is full.
pub struct Mailbox<T> {
    /// Where to send the component's messages.
    pub sender: mpsc::Sender<T>,
    /// The receiving end, held by the running component (see [`Handover`]).
    receiver: Handover<mpsc::Receiver<T>>,
}

impl<T> Mailbox<T> {
    pub fn new() -> Mailbox<T> {
        Mailbox::with_capacity(MAILBOX)
    }

    /// A mailbox that holds `capacity` messages before its senders wait.
    pub fn with_capacity(capacity: usize) -> Mailbox<T> {
        let (sender, receiver) = mpsc::channel(capacity);
        Mailbox {
            sender,
            receiver: Handover::new(receiver),
        }
    }

    /// Another handle on the same mailbox (for the component's links).
    pub fn share(&self) -> Mailbox<T> {
        Mailbox {
            sender: self.sender.clone(),
            receiver: self.receiver.share(),
        }
    }

    /// Takes the receiving end for the caller's life.
    pub async fn take(&self) -> OwnedMutexGuard<mpsc::Receiver<T>> {
        self.receiver.take().await
    }
}

impl<T> Default for Mailbox<T> {
    fn default() -> Self {
        Mailbox::new()
    }
}
