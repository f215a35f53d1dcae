//! A controller that runs several jobs at once ([`Executions`]): a conveyor that moves
//! several pallets, each move its own job (`[controller] jobs_at_once`,
//! docs/material-flow.md, "Transporters"). One [`ExecutionMachine`] per lane, all on
//! the one controller connection; each lane numbers its commands apart from the others
//! (lane `i` of `n`: `i + 1`, `i + 1 + n`, ...), so a reply, matched by its id, reaches
//! the lane that sent the command. With one lane every event goes to it unchanged: the
//! machine as [`crate::machine::execution`] documents it.
//!
//! | event | goes to | the lanes' actions |
//! |---|---|---|
//! | start | the first `ready` lane; none (all run, or the controller is not ready): the first lane, which refuses it (`busy` / `unavailable`) | as that lane's |
//! | abort | every lane (those running tell the controller; the dialect's abort stops all it runs) | one `AbortController` |
//! | controller status | every lane (they share the controller) | each distinct action once: one `Ready`, one `Unavailable`, every `Finished` |
//! | reply / command failure / departed, id `n` | the lane whose step waits for command `n`; none: nobody (late) | as that lane's |
//! | step status of `<conversation>#<i>` | the lane running that step; none: nobody | as that lane's |

use std::sync::Arc;

use robot_bridge::client::ControllerEvent;

use super::{ExecutionAction, ExecutionEvent, ExecutionMachine, ExecutionState};
use crate::catalog::ServiceCatalog;

/// The execution machines of one controller, one per job it runs at once.
#[derive(Debug, Clone)]
pub struct Executions {
    /// The lanes, each a machine with its own command ids; at least one.
    lanes: Vec<ExecutionMachine>,
}

/// A job a lane runs, as its view shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct LaneJob<'a> {
    /// The job's conversation.
    pub conversation_id: &'a str,
    /// The action of its step in progress, e.g. `move`.
    pub step: Option<String>,
}

impl Executions {
    /// `jobs_at_once` lanes (at least one) over `catalog`, fenced or not.
    pub fn new(catalog: Arc<ServiceCatalog>, fenced: bool, jobs_at_once: usize) -> Self {
        let n = jobs_at_once.max(1) as u64;
        let lanes = (0..n)
            .map(|i| {
                ExecutionMachine::new(catalog.clone())
                    .fenced(fenced)
                    .with_command_ids(i + 1, n)
            })
            .collect();
        Executions { lanes }
    }

    /// Lane `lane`'s machine.
    pub fn lane(&self, lane: usize) -> &ExecutionMachine {
        &self.lanes[lane]
    }

    /// The controller, as the lanes last heard of it (they all hear every status).
    pub fn controller(&self) -> schemas::ControllerStatus {
        self.lanes[0].controller()
    }

    /// The jobs running, lane by lane.
    pub fn running(&self) -> impl Iterator<Item = LaneJob<'_>> {
        self.lanes.iter().filter_map(|lane| {
            Some(LaneJob {
                conversation_id: lane.current_conversation()?,
                step: lane.current_step(),
            })
        })
    }

    /// As the transition log shows it: one lane's state (`ready`, `step 2`), or each
    /// lane's (`step 1 | ready | step 2`).
    pub fn describe(&self) -> String {
        let states: Vec<String> = self.lanes.iter().map(|l| l.state().to_string()).collect();
        states.join(" | ")
    }

    /// One event through the lane(s) it concerns (the table above): the actions, each
    /// with the lane it came from.
    pub fn handle(&mut self, event: ExecutionEvent) -> Vec<(usize, ExecutionAction)> {
        if self.lanes.len() == 1 {
            return tagged(0, self.lanes[0].handle(event));
        }
        match event {
            ExecutionEvent::Start(job) => {
                let lane = self
                    .lanes
                    .iter()
                    .position(|l| matches!(l.state(), ExecutionState::Ready))
                    .unwrap_or(0);
                tagged(lane, self.lanes[lane].handle(ExecutionEvent::Start(job)))
            }
            ExecutionEvent::Abort => self.every_lane(ExecutionEvent::Abort),
            ExecutionEvent::Controller(ControllerEvent::Status(..)) => self.every_lane(event),
            ExecutionEvent::Controller(
                ControllerEvent::Reply { id, .. }
                | ControllerEvent::CommandFailed { id, .. }
                | ControllerEvent::Departed { id },
            ) => match self.lanes.iter().position(|l| l.is_waiting_for(id)) {
                Some(lane) => tagged(lane, self.lanes[lane].handle(event)),
                None => vec![],
            },
            ExecutionEvent::Controller(ControllerEvent::StepStatus { ref step, .. }) => {
                let lane = self.lanes.iter().position(|l| {
                    l.current_step_index().is_some_and(|(conversation, i)| {
                        format!("{conversation}#{i}") == step.as_str()
                    })
                });
                match lane {
                    Some(lane) => tagged(lane, self.lanes[lane].handle(event)),
                    None => vec![],
                }
            }
        }
    }

    /// `event` to every lane; an action that more than one lane gives (the agenda told
    /// the controller is ready, the controller told to abort) is kept once.
    fn every_lane(&mut self, event: ExecutionEvent) -> Vec<(usize, ExecutionAction)> {
        let mut actions: Vec<(usize, ExecutionAction)> = Vec::new();
        for (i, lane) in self.lanes.iter_mut().enumerate() {
            for action in lane.handle(event.clone()) {
                let shared = matches!(
                    action,
                    ExecutionAction::Ready
                        | ExecutionAction::Unavailable(..)
                        | ExecutionAction::AbortController
                        | ExecutionAction::StateChanged
                );
                if shared && actions.iter().any(|(_, a)| *a == action) {
                    continue;
                }
                actions.push((i, action));
            }
        }
        actions
    }
}

fn tagged(lane: usize, actions: Vec<ExecutionAction>) -> Vec<(usize, ExecutionAction)> {
    actions.into_iter().map(|a| (lane, a)).collect()
}

#[cfg(test)]
mod tests;
