//! The server's doors while it runs: the sessions of users removed or changed in the
//! users file end, and the doors' figures (`Cell/Security`) are counted every second.

use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::info;

use super::users::{self, CellAuth};
use super::{queue, Input};

/// Ends the sessions of users removed or changed in the users file (every
/// [`users::USERS_CHECKED_EVERY`]), until `shutdown`. Their calls were refused from the
/// change on already ([`CellAuth::role_of`]).
pub(super) async fn end_sessions_of_changed_users(
    auth: Arc<CellAuth>,
    handle: opcua_server::ServerHandle,
    shutdown: CancellationToken,
) {
    if auth.users.path().is_none() {
        return;
    }
    let mut last = auth.users.get();
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = tokio::time::sleep(users::USERS_CHECKED_EVERY) => {}
        }
        let now = auth.users.get();
        if Arc::ptr_eq(&now, &last) {
            continue;
        }
        last = now;
        let mut ended = Vec::new();
        let closed = handle
            .session_manager()
            .write()
            .close_sessions_where(|session| {
                let end = session.user_token().is_some_and(|token| auth.ended(token));
                if end {
                    ended.push(CellAuth::who(session.user_token().expect("checked")));
                }
                end
            });
        if closed > 0 {
            info!(sessions = closed, users = ?ended, "OPC UA sessions ended: their users were removed or changed in the users file");
        }
    }
}

/// Counts the server's doors for `Cell/Security` every second, until `shutdown`.
pub(super) async fn count_the_doors(
    auth: Arc<CellAuth>,
    handle: opcua_server::ServerHandle,
    inputs: mpsc::Sender<Input>,
    dropped: Arc<AtomicU64>,
    shutdown: CancellationToken,
) {
    let mut every = tokio::time::interval(Duration::from_secs(1));
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = every.tick() => {}
        }
        let (activated, waiting) = handle.session_manager().read().counts();
        let figures = [
            auth.logins.refused_total(),
            auth.logins.in_check() as u64,
            activated as u64,
            waiting as u64,
        ];
        queue(&inputs, &dropped, Input::Doors(figures));
    }
}
