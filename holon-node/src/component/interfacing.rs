//! The interfacing component: robot-bridge's controller client, fed by the command
//! mailbox and reporting to the execution component's controller mailbox. A fenced
//! resource runs it with the fence's port ([`client::run_fenced`]): the same
//! connection then claims the controller, heartbeats and writes epochs and step ids.

use std::sync::Arc;

use holon::ChildError;
use robot_bridge::client::{
    self, ClientConfig, ControllerEvent, ControllerRequest, Epoch, FenceEvent, FencePort,
};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::warn;

use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::views::FenceView;

/// What the interfacing component is linked to.
pub struct Links {
    /// Where the controller is, and the protocol's timeouts.
    pub controller: ClientConfig,
    /// Commands from the execution component.
    pub commands: Mailbox<ControllerRequest>,
    /// The execution component's controller mailbox.
    pub events: mpsc::Sender<ControllerEvent>,
    /// The fence's port, for a fenced resource: taken by the running component and
    /// handed to its successor, like a mailbox.
    pub fence: Option<Handover<FencePort>>,
    /// Whether the resource holds the claim (the node's fence loop writes it): a
    /// successor started while it does reports the claim lost with its predecessor's
    /// connection.
    pub fence_view: watch::Receiver<FenceView>,
    /// Its fault to inject on request.
    pub faults: Arc<Faults>,
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let mut commands = links.commands.take().await;
    let events = links.events.clone();
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
    let client = async {
        match port.as_deref_mut() {
            Some(port) => {
                client::run_fenced(config, &mut commands, port, events, token.clone()).await
            }
            None => client::run(config, &mut commands, events, token.clone()).await,
        }
    };
    tokio::select! {
        _ = client => {
            if token.is_cancelled() { Ok(()) } else { Err("the controller client stopped".into()) }
        }
        _ = links.faults.interfacing.notified() => panic!("fault injection: interfacing crashed"),
    }
}
