//! The phases of a holon process's life and the events between them: the one table the
//! driver ([`super::driver`]) follows, pure (no I/O), and the source of the diagram in
//! docs/architecture.md ("One life cycle, one driver", checked by this module's tests).
//!
//! | from | event | to |
//! |---|---|---|
//! | opening | opened | claiming |
//! | opening | shutdown | closed |
//! | opening | failed | closed |
//! | claiming | won | starting |
//! | claiming | shutdown | closed |
//! | claiming | failed | closed |
//! | starting | started | holding |
//! | starting | failed | closed |
//! | holding | held | serving |
//! | holding | shutdown | leaving |
//! | holding | work_ended | leaving |
//! | holding | failed | leaving |
//! | serving | successor_asks | handing_over |
//! | serving | shutdown | leaving |
//! | serving | work_ended | leaving |
//! | serving | deposed | stepping_down |
//! | handing_over | refused | serving |
//! | handing_over | prepared | standing_in |
//! | handing_over | shutdown | leaving |
//! | standing_in | served | closed |
//! | standing_in | shutdown | closed |
//! | standing_in | no_successor | closed |
//! | leaving | left | closed |
//! | stepping_down | again | claiming |
//! | stepping_down | ended | closed |
//!
//! `claiming` is the leadership's step before the work starts (the name's liveliness
//! claim, the etcd campaign: a standby waits there); `holding` its step once the work
//! runs (the controller fence claims through the resource's controller connection: a
//! fenced standby waits there). A strategy with nothing to do in a step passes through
//! it at once.

use std::fmt;

/// Where a holon process is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Phase {
    /// The session opens as the process's identity; with `--take-over` the running
    /// process of the name hands over first.
    Opening,
    /// The leadership before the work starts: the name claimed (a twin refused), or
    /// the etcd leader key campaigned for.
    Claiming,
    /// The holon's own work starts (its components, queryables, journal).
    Starting,
    /// The leadership once the work runs: the controller fence claimed.
    Holding,
    /// The token declared: the holon serves, and answers successors.
    Serving,
    /// A successor asked: the holon finishes what it must before it lets go.
    HandingOver,
    /// Handed over: token withdrawn, successor released, a stand-in answers until the
    /// successor serves.
    StandingIn,
    /// Stopping: work withdrawn, token withdrawn, work stopped.
    Leaving,
    /// Deposed: token withdrawn, work stopped; the leadership says what follows.
    SteppingDown,
    /// The session is closed (within its budget): the process ends.
    Closed,
}

/// What moves a holon from one phase to the next.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Event {
    /// The session is open (and the predecessor, if any, handed over).
    Opened,
    /// The leadership was won before the start.
    Won,
    /// The holon's work started.
    Started,
    /// The leadership holds with the work running; the token is declared.
    Held,
    /// A successor asked to take over and may.
    SuccessorAsks,
    /// The hand-over was refused or abandoned: the holon serves on.
    Refused,
    /// The holon finished what it must: it lets go.
    Prepared,
    /// The successor serves.
    Served,
    /// No successor served within the stand-in limit (the process exits 1).
    NoSuccessor,
    /// SIGTERM / Ctrl-C.
    Shutdown,
    /// The holon's work ended on its own (its supervisor gave up).
    WorkEnded,
    /// The leadership was lost (the controller or etcd says another holds it).
    Deposed,
    /// Withdrawn and stopped.
    Left,
    /// Stepped down; the leadership claims again.
    Again,
    /// Stepped down; the leadership ends the process.
    Ended,
    /// A step failed (the session, the claim, the start): the process ends with it.
    Failed,
}

/// Every transition: `(from, event, to)`. The only place the life's order is written.
pub const TRANSITIONS: &[(Phase, Event, Phase)] = {
    use Event::*;
    use Phase::*;
    &[
        (Opening, Opened, Claiming),
        (Opening, Shutdown, Closed),
        (Opening, Failed, Closed),
        (Claiming, Won, Starting),
        (Claiming, Shutdown, Closed),
        (Claiming, Failed, Closed),
        (Starting, Started, Holding),
        (Starting, Failed, Closed),
        (Holding, Held, Serving),
        (Holding, Shutdown, Leaving),
        (Holding, WorkEnded, Leaving),
        (Holding, Failed, Leaving),
        (Serving, SuccessorAsks, HandingOver),
        (Serving, Shutdown, Leaving),
        (Serving, WorkEnded, Leaving),
        (Serving, Deposed, SteppingDown),
        (HandingOver, Refused, Serving),
        (HandingOver, Prepared, StandingIn),
        (HandingOver, Shutdown, Leaving),
        (StandingIn, Served, Closed),
        (StandingIn, Shutdown, Closed),
        (StandingIn, NoSuccessor, Closed),
        (Leaving, Left, Closed),
        (SteppingDown, Again, Claiming),
        (SteppingDown, Ended, Closed),
    ]
};

/// The phase `event` leads to from `from`; `None` if the table has no such transition.
pub fn next(from: Phase, event: Event) -> Option<Phase> {
    TRANSITIONS
        .iter()
        .find(|(f, e, _)| *f == from && *e == event)
        .map(|(_, _, to)| *to)
}

/// The table as a mermaid state diagram (docs/architecture.md holds this text).
pub fn mermaid() -> String {
    let mut text = String::from("stateDiagram-v2\n    [*] --> opening\n");
    for (from, event, to) in TRANSITIONS {
        let to = match to {
            Phase::Closed => "[*]".to_string(),
            to => to.to_string(),
        };
        text.push_str(&format!("    {from} --> {to}: {event}\n"));
    }
    text
}

/// snake_case, as the table and the diagram write it.
fn snake(debug: String) -> String {
    let mut out = String::new();
    for (i, c) in debug.chars().enumerate() {
        if c.is_uppercase() {
            if i > 0 {
                out.push('_');
            }
            out.extend(c.to_lowercase());
        } else {
            out.push(c);
        }
    }
    out
}

impl fmt::Display for Phase {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&snake(format!("{self:?}")))
    }
}

impl fmt::Display for Event {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&snake(format!("{self:?}")))
    }
}

/// A holon's life as it goes: its phase, moved only along [`TRANSITIONS`].
#[derive(Debug)]
pub struct Machine {
    /// How the holon is named in the log.
    holder: String,
    /// Where it is now.
    phase: Phase,
}

impl Machine {
    /// A life that is opening.
    pub fn new(holder: &str) -> Machine {
        Machine {
            holder: holder.to_string(),
            phase: Phase::Opening,
        }
    }

    /// Where the holon is.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Moves on `event`. A move the table does not have is the driver's bug: it is
    /// logged, and the phase stays (debug builds panic, so tests find it).
    pub fn on(&mut self, event: Event) -> Phase {
        match next(self.phase, event) {
            Some(to) => {
                tracing::debug!(holon = %self.holder, from = %self.phase, %event, %to, "life");
                self.phase = to;
            }
            None => {
                tracing::error!(holon = %self.holder, phase = %self.phase, %event, "the life cycle has no such transition");
                debug_assert!(false, "no transition from {} on {event}", self.phase);
            }
        }
        self.phase
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL_PHASES: [Phase; 10] = [
        Phase::Opening,
        Phase::Claiming,
        Phase::Starting,
        Phase::Holding,
        Phase::Serving,
        Phase::HandingOver,
        Phase::StandingIn,
        Phase::Leaving,
        Phase::SteppingDown,
        Phase::Closed,
    ];

    /// The rows `| from | event | to |` of a markdown table in `text`.
    fn table_rows(text: &str, prefix: &str) -> Vec<(String, String, String)> {
        text.lines()
            .filter_map(|line| line.trim_start().strip_prefix(prefix))
            .filter_map(|row| {
                let cells: Vec<&str> = row.trim().trim_matches('|').split('|').collect();
                match cells.as_slice() {
                    [from, event, to] => Some((
                        from.trim().to_string(),
                        event.trim().to_string(),
                        to.trim().to_string(),
                    )),
                    _ => None,
                }
            })
            .filter(|(from, _, _)| from != "from" && !from.starts_with("---"))
            .collect()
    }

    fn table() -> Vec<(String, String, String)> {
        TRANSITIONS
            .iter()
            .map(|(f, e, t)| (f.to_string(), e.to_string(), t.to_string()))
            .collect()
    }

    #[test]
    fn the_doc_comment_table_is_the_code() {
        let rows = table_rows(include_str!("machine.rs"), "//! ");
        assert_eq!(rows, table());
    }

    #[test]
    fn the_architecture_diagram_is_the_code() {
        let doc = include_str!("../../../docs/architecture.md");
        let start = doc
            .find("```mermaid\nstateDiagram-v2")
            .expect("docs/architecture.md has the life's diagram");
        let body = &doc[start + "```mermaid\n".len()..];
        let end = body.find("```").expect("the diagram ends");
        assert_eq!(
            &body[..end],
            mermaid(),
            "regenerate the diagram with holon::life::machine::mermaid()"
        );
    }

    #[test]
    fn every_phase_is_reached_and_every_event_is_used() {
        for phase in ALL_PHASES {
            let reached =
                phase == Phase::Opening || TRANSITIONS.iter().any(|(_, _, to)| *to == phase);
            assert!(reached, "{phase} is never reached");
            let left =
                phase == Phase::Closed || TRANSITIONS.iter().any(|(from, _, _)| *from == phase);
            assert!(left, "{phase} is never left");
        }
        use Event::*;
        for event in [
            Opened,
            Won,
            Started,
            Held,
            SuccessorAsks,
            Refused,
            Prepared,
            Served,
            NoSuccessor,
            Shutdown,
            WorkEnded,
            Deposed,
            Left,
            Again,
            Ended,
            Failed,
        ] {
            assert!(
                TRANSITIONS.iter().any(|(_, e, _)| *e == event),
                "{event} unused"
            );
        }
    }

    #[test]
    fn one_transition_per_phase_and_event() {
        for (i, (from, event, _)) in TRANSITIONS.iter().enumerate() {
            assert!(
                !TRANSITIONS[..i]
                    .iter()
                    .any(|(f, e, _)| f == from && e == event),
                "{from} on {event} twice"
            );
        }
    }

    #[test]
    fn a_hand_over_that_is_refused_serves_on() {
        let mut life = Machine::new("resource/r");
        for event in [Event::Opened, Event::Won, Event::Started, Event::Held] {
            life.on(event);
        }
        assert_eq!(life.on(Event::SuccessorAsks), Phase::HandingOver);
        assert_eq!(life.on(Event::Refused), Phase::Serving);
        assert_eq!(life.on(Event::SuccessorAsks), Phase::HandingOver);
        assert_eq!(life.on(Event::Prepared), Phase::StandingIn);
        assert_eq!(life.on(Event::Served), Phase::Closed);
    }

    #[test]
    fn a_deposed_standby_claims_again() {
        let mut life = Machine::new("resource/r");
        for event in [
            Event::Opened,
            Event::Won,
            Event::Started,
            Event::Held,
            Event::Deposed,
        ] {
            life.on(event);
        }
        assert_eq!(life.phase(), Phase::SteppingDown);
        assert_eq!(life.on(Event::Again), Phase::Claiming);
    }
}
