//! The cell's layout, as a transporter needs it (docs/material-flow.md): where the
//! locations it moves parts between are is their holons' to state, so a transporter asks
//! every serving resource's part (`resource/*/layout`) when it starts, whenever a
//! resource appears or vanishes (its token), and every [`ASK_EVERY`] besides, and hands
//! the agenda manager the layout when it changed
//! ([`AgendaEvent::Layout`]): the agenda times its moves by it and refuses those it
//! cannot make. Only a resource whose `[layout]` makes it a transporter runs it.

use std::sync::Arc;
use std::time::Duration;

use holon::ChildError;
use schemas::layout::{CellLayout, LayoutPart};
use schemas::{CellKeys, HolonId, HolonKind};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

use crate::agenda::AgendaEvent;
use crate::component::agenda_manager::AgendaMessage;

/// How often the layout is asked again (a station started or stopped is in it within
/// this).
pub const ASK_EVERY: Duration = Duration::from_secs(5);

/// How long one ask waits for the parts.
const ASK_TIMEOUT: Duration = Duration::from_secs(2);

pub struct Links {
    pub holon: HolonId,
    pub session: zenoh::Session,
    pub keys: CellKeys,
    /// This resource's own part (in the layout whether or not it answered yet).
    pub own: LayoutPart,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
}

/// The parts the serving resources answer, this one's own among them.
async fn ask(links: &Links) -> Result<CellLayout, zenoh::Error> {
    let answered = holon::layout::ask(&links.session, &links.keys, ASK_TIMEOUT).await?;
    for why in &answered.unreadable {
        debug!(holon = %links.holon, %why, "left out of the layout");
    }
    let others = answered
        .parts
        .into_iter()
        .filter(|part| part.holon != links.own.holon);
    Ok(CellLayout::assemble(
        std::iter::once(links.own.clone()).chain(others),
    ))
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = &links.holon;
    // A station started or stopped: its part is in the layout (or out of it) at once,
    // not at the next tick (its layout is answered before its token appears).
    let resources = links
        .session
        .liveliness()
        .declare_subscriber(links.keys.alive_kind(HolonKind::Resource))
        .await?;
    let mut known: Option<CellLayout> = None;
    let mut every = tokio::time::interval(ASK_EVERY);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = every.tick() => {}
            change = resources.recv_async() => {
                change.map_err(|_| "the resources' liveliness subscription closed")?;
                // Those of the same moment make one ask.
                while let Ok(Some(_)) = resources.try_recv() {}
            }
        }
        let layout = match ask(&links).await {
            Ok(layout) => layout,
            Err(e) => {
                debug!(%holon, error = %e, "cannot ask for the cell's layout; asked again shortly");
                continue;
            }
        };
        if known.as_ref() == Some(&layout) {
            continue;
        }
        info!(%holon, holons = layout.parts.len(), problems = layout.problems.len(), "the cell's layout as this transporter knows it");
        links
            .agenda
            .send(AgendaEvent::Layout(Arc::new(layout.clone())).into())
            .await
            .map_err(|_| "agenda mailbox closed")?;
        known = Some(layout);
    }
}
