//! Asking for the cell's layout (docs/material-flow.md): every serving resource answers
//! its own part on `resource/<name>/layout`. `cell layout`, the dashboard and a
//! transporter's layout component ask this way.

use std::time::Duration;

use schemas::layout::LayoutPart;
use schemas::CellKeys;

/// What the serving resources answered.
#[derive(Debug, Default)]
pub struct Answered {
    /// Each resource's part.
    pub parts: Vec<LayoutPart>,
    /// Answers that are not a layout part: the key and why.
    pub unreadable: Vec<String>,
}

/// Asks every serving resource for its part of the layout, waiting at most `timeout`.
pub async fn ask(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Answered, zenoh::Error> {
    let mut replies = session
        .get(keys.layout_all())
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(timeout)
        .with(crate::query::replies())
        .await?;
    let mut answered = Answered::default();
    while let Some(reply) = replies.recv().await {
        let Ok(sample) = reply.result() else { continue };
        match LayoutPart::from_json(&sample.payload().to_bytes()) {
            Ok(part) => answered.parts.push(part),
            Err(e) => answered.unreadable.push(format!(
                "{}: an answer that is not a layout part: {e}",
                sample.key_expr()
            )),
        }
    }
    Ok(answered)
}

/// How often [`follow`] asks again besides when a resource appears or vanishes (a
/// station started or stopped is in the layout within this).
pub const ASK_EVERY: Duration = Duration::from_secs(5);

/// How long one of [`follow`]'s asks waits for the parts.
const ASK_TIMEOUT: Duration = Duration::from_secs(2);

/// Follows the cell's layout until `token` is cancelled: asks every serving resource's
/// part when it starts, whenever a resource's token appears or vanishes, and every
/// [`ASK_EVERY`], and writes the assembled layout to `layout` when it changed. `own`,
/// a resource's own part, is in the layout whether or not it answered yet. An ask that
/// fails is logged and made again at the next occasion; the error is only the
/// subscription to the resources' tokens, which cannot be declared. It ends too when the
/// session closes.
pub async fn follow(
    session: &zenoh::Session,
    keys: &CellKeys,
    own: Option<&LayoutPart>,
    layout: &tokio::sync::watch::Sender<Option<std::sync::Arc<schemas::layout::CellLayout>>>,
    token: &tokio_util::sync::CancellationToken,
) -> Result<(), zenoh::Error> {
    // With the tokens already there (history): zenoh 1.10.2's client routing knows a
    // token only once declared to it, and logs `Unknown token` at ERROR for each
    // departure of one that was not (docs/operations.md, "zenoh's own log lines").
    let resources = session
        .liveliness()
        .declare_subscriber(keys.alive_kind(schemas::HolonKind::Resource))
        .history(true)
        .await?;
    let mut every = tokio::time::interval(ASK_EVERY);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = every.tick() => {}
            change = resources.recv_async() => {
                if change.is_err() {
                    // Only a closing session ends the subscription (it is not undeclared
                    // while following): nothing left to follow.
                    tracing::debug!("the resources' liveliness subscription closed: the layout is no longer followed");
                    return Ok(());
                }
                // Those of the same moment make one ask.
                while let Ok(Some(_)) = resources.try_recv() {}
            }
        }
        let answered = match ask(session, keys, ASK_TIMEOUT).await {
            Ok(answered) => answered,
            Err(e) => {
                tracing::debug!(error = %e, "cannot ask for the cell's layout; asked again shortly");
                continue;
            }
        };
        for why in &answered.unreadable {
            tracing::debug!(%why, "left out of the layout");
        }
        let others = answered
            .parts
            .into_iter()
            .filter(|part| own.is_none_or(|own| part.holon != own.holon));
        let assembled =
            schemas::layout::CellLayout::assemble(own.cloned().into_iter().chain(others));
        layout.send_if_modified(|known| {
            if known.as_deref() == Some(&assembled) {
                return false;
            }
            *known = Some(std::sync::Arc::new(assembled));
            true
        });
    }
}

/// The cell's layout as a task of its own follows it ([`follow`]), until dropped: for
/// holons that read the layout now and then (an order-node's orders, a staff holon).
pub struct Follower {
    /// The layout as last assembled (`None` until the first answers).
    layout: tokio::sync::watch::Receiver<Option<std::sync::Arc<schemas::layout::CellLayout>>>,
    /// Stops the following when dropped.
    _stop: tokio_util::sync::DropGuard,
}

impl Follower {
    /// Starts following on `session`; the first ask goes at once, its answers come
    /// within a few seconds.
    pub fn start(session: &zenoh::Session, keys: &CellKeys) -> Follower {
        let (sender, layout) = tokio::sync::watch::channel(None);
        let stop = tokio_util::sync::CancellationToken::new();
        let (session, keys, token) = (session.clone(), keys.clone(), stop.clone());
        tokio::spawn(async move {
            match follow(&session, &keys, None, &sender, &token).await {
                Ok(()) => {}
                // The holon is stopping: its session closed under the follower.
                Err(e) if session.is_closed() => {
                    tracing::debug!(error = %e, "the session closed: the layout is no longer followed")
                }
                Err(e) => {
                    tracing::error!(error = %e, "cannot follow the cell's layout: what needs it waits or goes without")
                }
            }
        });
        Follower {
            layout,
            _stop: stop.drop_guard(),
        }
    }

    /// Waits at most `within` for the first answers: whether they came.
    pub async fn first(&mut self, within: Duration) -> bool {
        if self.layout.borrow().is_some() {
            return true;
        }
        tokio::time::timeout(within, self.layout.changed())
            .await
            .is_ok_and(|changed| changed.is_ok())
    }

    /// The layout as it stands (`None` while no resource has answered its part).
    pub fn latest(&self) -> Option<std::sync::Arc<schemas::layout::CellLayout>> {
        self.layout.borrow().clone()
    }
}
