//! The interfacing component: robot-bridge's controller client, fed by the command
//! mailbox and reporting to the execution component's controller mailbox. A fenced
//! resource runs it with the fence's port ([`client::run_fenced`]): the same
//! connection then claims the controller, heartbeats and writes epochs and step ids.

use std::sync::Arc;

use holon::ChildError;
use robot_bridge::client::{self, ClientConfig, ControllerEvent, ControllerRequest, FencePort};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};

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
