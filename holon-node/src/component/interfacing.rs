//! The interfacing component: robot-bridge's controller client, run by the execution
//! component's task for the execution ([`client::drive`], the execution being its
//! [`client::Owner`]). It is the seed's interfacing component as a module: it owns the
//! controller connection and speaks the controller's dialect; the execution gives it
//! commands and learns the controller's events by calling it, with no queue between.
//!
//! A fenced resource runs the client with the fence's port: the same connection then
//! claims the controller, heartbeats and writes epochs and step ids.

use robot_bridge::client::{self, ClientConfig, Epoch, FenceEvent, FencePort, Owner};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::warn;

use crate::handover::Handover;
use crate::views::FenceView;

/// What the interfacing component is linked to.
pub struct Links {
    /// Where the controller is, and the protocol's timeouts.
    pub controller: ClientConfig,
    /// The fence's port, for a fenced resource: taken by the running component and
    /// handed to its successor, like a mailbox.
    pub fence: Option<Handover<FencePort>>,
    /// Whether the resource holds the claim (the node's fence loop writes it): a
    /// successor started while it does reports the claim lost with its predecessor's
    /// connection.
    pub fence_view: watch::Receiver<FenceView>,
}

impl Links {
    /// Whether the resource is fenced: its commands carry step ids.
    pub fn fenced(&self) -> bool {
        self.fence.is_some()
    }
}

/// Runs the controller client for `owner` until `token` is cancelled or the owner is
/// gone.
pub async fn serve<O: Owner>(links: &Links, owner: &mut O, token: CancellationToken) {
    let mut port = match &links.fence {
        Some(fence) => Some(fence.take().await),
        None => None,
    };
    if let (Some(port), FenceView::Holding(epoch)) = (&port, *links.fence_view.borrow()) {
        // A restart: the claim went with the predecessor's connection.
        let lost = FenceEvent::Lost {
            epoch: Epoch(epoch),
        };
        if port.events.try_send(lost).is_err() {
            warn!(
                epoch,
                "cannot report the claim lost with the restarted controller client"
            );
        }
    }
    let config = links.controller.clone();
    client::drive(config, owner, port.as_deref_mut(), token).await
}
