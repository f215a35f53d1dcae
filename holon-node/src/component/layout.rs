//! The cell's layout, as a transporter needs it (docs/material-flow.md): where the
//! locations it moves parts between are is their holons' to state, so a transporter
//! follows every serving resource's part (`resource/*/layout`, [`holon::layout::follow`]:
//! when it starts, whenever a resource appears or vanishes, and every
//! [`holon::layout::ASK_EVERY`]) and hands the agenda manager the layout when it changed
//! ([`AgendaEvent::Layout`]): the agenda times its moves by it and refuses those it
//! cannot make. Only a resource whose `[layout]` makes it a transporter runs it.

use std::sync::Arc;

use holon::ChildError;
use schemas::layout::LayoutPart;
use schemas::{CellKeys, HolonId};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::info;

use crate::component::agenda_manager::AgendaMessage;
use crate::machine::agenda::AgendaEvent;

pub struct Links {
    pub holon: HolonId,
    pub session: zenoh::Session,
    pub keys: CellKeys,
    /// This resource's own part (in the layout whether or not it answered yet).
    pub own: LayoutPart,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = &links.holon;
    let (known, mut changes) = watch::channel(None);
    let follow = holon::layout::follow(
        &links.session,
        &links.keys,
        Some(&links.own),
        &known,
        &token,
    );
    tokio::pin!(follow);
    loop {
        tokio::select! {
            followed = &mut follow => return followed,
            changed = changes.changed() => {
                changed.map_err(|_| "the layout's watch closed")?;
                let Some(layout) = changes.borrow_and_update().clone() else { continue };
                info!(%holon, holons = layout.parts.len(), problems = layout.problems.len(), "the cell's layout as this transporter knows it");
                links
                    .agenda
                    .send(AgendaEvent::Layout(layout).into())
                    .await
                    .map_err(|_| "agenda mailbox closed")?;
            }
        }
    }
}
