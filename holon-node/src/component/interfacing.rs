//! The interfacing component: robot-bridge's controller client, fed by the command
//! mailbox and reporting to the execution component's controller mailbox.

use std::sync::Arc;

use holon::ChildError;
use robot_bridge::client::{self, ClientConfig, ControllerEvent, ControllerRequest};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use crate::fault_injection::Faults;
use crate::handover::Mailbox;

/// What the interfacing component is linked to.
pub struct Links {
    /// Where the controller is, and the protocol's timeouts.
    pub controller: ClientConfig,
    /// Commands from the execution component.
    pub commands: Mailbox<ControllerRequest>,
    /// The execution component's controller mailbox.
    pub events: mpsc::Sender<ControllerEvent>,
    pub faults: Arc<Faults>,
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let mut commands = links.commands.take().await;
    let events = links.events.clone();
    tokio::select! {
        _ = client::run(links.controller.clone(), &mut commands, events, token.clone()) => {
            if token.is_cancelled() { Ok(()) } else { Err("the controller client stopped".into()) }
        }
        _ = links.faults.interfacing.notified() => panic!("fault injection: interfacing crashed"),
    }
}
