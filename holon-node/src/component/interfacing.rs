//! The interfacing component: robot-bridge's controller client, run by the execution
//! component's task for the execution ([`client::drive`], the execution being its
//! [`client::Owner`]). It is the seed's interfacing component as a module: it owns the
//! controller connection and speaks the controller's dialect; the execution gives it
//! commands and learns the controller's events by calling it, with no queue between.
//!
//! A fenced resource runs the client with the fence's port: the same connection then
//! claims the controller, heartbeats and writes epochs and step ids.
//!
//! Its connection attempts are paced by the project's backoff ([`Reconnecting`], a
//! [`holon::Backoff`]): from `reconnect_interval` doubling up to `reconnect_max` while
//! attempts fail or connections end without having served, back to
//! `reconnect_interval` after one that served.

use std::time::Duration;

use holon::Backoff;
use robot_bridge::client::{
    self, ClientConfig, Epoch, FenceEvent, FencePort, LinkEnd, Owner, Reconnect,
};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::handover::Handover;
use crate::views::FenceView;

/// What the interfacing component is linked to.
pub struct Links {
    /// Where the controller is, and the protocol's timeouts.
    pub controller: ClientConfig,
    /// The longest pause before reconnecting (`controller.reconnect_max_ms`).
    pub reconnect_max: Duration,
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
    let mut paced = Logged {
        machine: Reconnecting::new(config.reconnect_interval, links.reconnect_max),
        controller: config.address.clone(),
    };
    client::drive(config, owner, &mut paced, port.as_deref_mut(), token).await
}

/// The pause before each connection attempt: the machine of the controller link's
/// backoff, one [`LinkEnd`] in, one [`Pacing`] out.
///
/// A connection *served* when the controller answered at least one step on it (its
/// result or its failure: it speaks the dialect), or when it stayed up at least
/// `reconnect_max` (an idle cell sends no steps; a connection that lasted that long
/// kept the holon from reconnecting as long as the longest pause would). Anything else
/// did not serve: an attempt that made no connection (refused, unreachable, timed out)
/// and a connection that ended sooner, whatever ended it (a protocol error such as a
/// status outside its enum table, a reset or close, a timeout, garbage).
#[derive(Debug, Clone)]
pub struct Reconnecting {
    backoff: Backoff,
    max: Duration,
    /// The last pause given (none yet: `interval`).
    last: Duration,
}

/// What the machine decided for the next attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pacing {
    /// The pause before it.
    pub pause: Duration,
    /// How the backoff changed, if it did (what is logged).
    pub change: Option<Change>,
}

/// A change of the backoff: logged, where the attempts themselves are not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Change {
    /// Longer than the pause before (attempts keep failing).
    Grew,
    /// Back to `reconnect_interval` after a connection that served, from a longer
    /// pause.
    Reset,
}

impl Reconnecting {
    /// `max` below `interval` keeps every pause at `interval` (the config refuses it).
    pub fn new(interval: Duration, max: Duration) -> Reconnecting {
        Reconnecting {
            backoff: Backoff::new(interval, max),
            max: max.max(interval),
            last: interval,
        }
    }

    /// Whether a link that ended so served (see [`Reconnecting`]).
    pub fn served(&self, end: LinkEnd) -> bool {
        match end {
            LinkEnd::NotConnected => false,
            LinkEnd::Ended { lasted, answered } => answered > 0 || lasted >= self.max,
        }
    }

    /// The pause before the next attempt, after the last ended as `end`.
    pub fn handle(&mut self, end: LinkEnd) -> Pacing {
        let served = self.served(end);
        if served {
            self.backoff.reset();
        }
        let pause = self.backoff.next_pause();
        let change = if served {
            (self.last > pause).then_some(Change::Reset)
        } else {
            (pause > self.last).then_some(Change::Grew)
        };
        self.last = pause;
        Pacing { pause, change }
    }
}

/// The machine on the client's task, its changes logged.
struct Logged {
    machine: Reconnecting,
    controller: String,
}

impl Reconnect for Logged {
    fn pause(&mut self, last: LinkEnd) -> Duration {
        let pacing = self.machine.handle(last);
        let pause_ms = pacing.pause.as_millis() as u64;
        match pacing.change {
            Some(Change::Grew) => warn!(
                controller = %self.controller,
                pause_ms,
                max_ms = self.machine.max.as_millis() as u64,
                "controller connections keep failing or ending unserved; backing off"
            ),
            Some(Change::Reset) => info!(
                controller = %self.controller,
                pause_ms,
                "a controller connection served; the reconnect pause is back to its first"
            ),
            None => {}
        }
        pacing.pause
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: fn(u64) -> Duration = Duration::from_millis;

    fn ended(lasted_ms: u64, answered: u64) -> LinkEnd {
        LinkEnd::Ended {
            lasted: MS(lasted_ms),
            answered,
        }
    }

    #[test]
    fn pauses_double_to_the_cap_whatever_ended_the_link_and_start_over_after_one_that_served() {
        let mut machine = Reconnecting::new(MS(200), MS(1600));
        let unserved = [
            ended(5, 0),
            LinkEnd::NotConnected,
            ended(300, 0),
            LinkEnd::NotConnected,
            ended(1599, 0),
            ended(0, 0),
        ];
        let pauses: Vec<_> = unserved.map(|end| machine.handle(end).pause).to_vec();
        assert_eq!(pauses, [200, 400, 800, 1600, 1600, 1600].map(MS));
        // A step answered: served, however short.
        assert_eq!(
            machine.handle(ended(10, 1)),
            Pacing {
                pause: MS(200),
                change: Some(Change::Reset)
            }
        );
        assert_eq!(machine.handle(ended(10, 0)).pause, MS(400));
        // Up as long as the cap: served, with no step.
        assert_eq!(machine.handle(ended(1600, 0)).pause, MS(200));
        assert_eq!(machine.handle(ended(1600, 0)).pause, MS(200));
    }

    #[test]
    fn only_a_longer_pause_and_a_reset_from_one_are_changes() {
        let mut machine = Reconnecting::new(MS(200), MS(800));
        let changes: Vec<_> = [
            ended(0, 0),
            ended(0, 0),
            ended(0, 0),
            ended(0, 0),
            ended(0, 0),
            ended(0, 3),
            ended(0, 3),
        ]
        .map(|end| machine.handle(end).change)
        .to_vec();
        let (grew, reset) = (Some(Change::Grew), Some(Change::Reset));
        assert_eq!(changes, [None, grew, grew, None, None, reset, None]);
    }
}
