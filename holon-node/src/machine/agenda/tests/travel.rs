//! A transporter's moves: timed by the cell's layout, and refused where it cannot go.

use std::collections::BTreeMap;
use std::time::Duration;

use super::*;
use crate::catalog::{ServiceCatalog, ServiceDefinition, Step};
use schemas::layout::CellLayout;
use schemas::unix_ms;

fn part(holon: &str, toml_text: &str) -> schemas::layout::LayoutPart {
    schemas::layout::part_from_toml(holon, toml_text).unwrap_or_else(|e| panic!("{e}"))
}

/// conveyor1: a 4 m loop at 1 m/s, load at 0, robot1's port at 1 m, robot2's at 3 m.
fn layout() -> Arc<CellLayout> {
    let station = |dock: &str| {
        format!("[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n")
    };
    Arc::new(CellLayout::assemble([
        part(
            "conveyor1",
            "[[layout.locations]]\nname = \"load\"\nrole = \"entry_exit\"\ndock = \"conveyor1.load\"\n[layout.conveyor]\nlength_mm = 4000\nspeed_mm_s = 1000\npallets = 2\nstoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }, { name = \"s2\", at_mm = 3000 }]\n",
        ),
        part("robot1", &station("conveyor1.s1")),
        part("robot2", &station("conveyor1.s2")),
    ]))
}

fn conveyor() -> AgendaMachine {
    let transport = ServiceDefinition {
        steps: vec![Step {
            action: "move".into(),
            until: vec!["arrived".into()],
            position: None,
        }],
        nominal_duration: Duration::from_millis(500),
    };
    let catalog = ServiceCatalog::new(BTreeMap::from([("transport".to_string(), transport)]));
    let mut m = AgendaMachine::new(
        HolonId::resource("conveyor1").unwrap(),
        Arc::new(catalog),
        8,
        unix_ms(),
    );
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m
}

fn transport(kind: MessageType, conversation: &str, from: &str, to: &str) -> Service {
    let info = json!({"part": conversation, "from": from, "to": to});
    Service::request(
        kind,
        "transport",
        conversation,
        HolonId::order("o-1").unwrap(),
    )
    .with_reply_to(INBOX)
    .with_info(info.as_object().unwrap().clone())
}

#[test]
fn a_transporter_proposes_its_travel_time_and_the_moves_ahead() {
    let mut m = conveyor();
    let ask = |m: &mut AgendaMachine, from: &str, to: &str| {
        let actions = m.handle(
            AgendaEvent::Request(transport(MessageType::ProposalReq, "p", from, to)),
            unix_ms(),
        );
        reply(&actions).clone()
    };
    // Before it knows the layout: the nominal duration.
    assert_eq!(
        ask(&mut m, "conveyor1.load", "robot1.port").info["duration_ms"],
        500
    );
    assert!(m
        .handle(AgendaEvent::Layout(layout()), unix_ms())
        .is_empty());
    let proposal = ask(&mut m, "conveyor1.load", "robot1.port");
    assert_eq!(proposal.info["duration_ms"], 1000);
    // One way round: robot2's port to robot1's is 2 m, 2 s.
    assert_eq!(
        ask(&mut m, "robot2.port", "robot1.port").info["duration_ms"],
        2000
    );
    // Two moves booked ahead: their travel is the wait.
    for (c, from, to) in [
        ("c1", "conveyor1.load", "robot2.port"),
        ("c2", "robot2.port", "robot1.port"),
    ] {
        let actions = m.handle(
            AgendaEvent::Request(transport(MessageType::BookingReq, c, from, to)),
            unix_ms(),
        );
        assert_eq!(reply(&actions).result, Some(true), "{actions:?}");
    }
    assert_eq!(
        ask(&mut m, "robot1.port", "conveyor1.load").info["expected_wait_ms"],
        3000 + 2000
    );
}

#[test]
fn a_move_the_transporter_cannot_make_is_refused_with_why() {
    let mut m = conveyor();
    m.handle(AgendaEvent::Layout(layout()), unix_ms());
    let proposal = m.handle(
        AgendaEvent::Request(transport(
            MessageType::ProposalReq,
            "p",
            "conveyor1.load",
            "robot9.port",
        )),
        unix_ms(),
    );
    assert_refused(&proposal, "invalid_info");
    assert_eq!(
        reply(&proposal).info["detail"],
        "robot9.port is not in the cell's layout (no serving resource states it)"
    );
    let booking = m.handle(
        AgendaEvent::Request(transport(
            MessageType::BookingReq,
            "c1",
            "conveyor1.load",
            "robot9.port",
        )),
        unix_ms(),
    );
    assert_refused(&booking, "invalid_info");
    assert!(m.bookings.is_empty());
    // Both ends known, but on no way of this transporter's.
    let mut apart = (*layout()).clone();
    apart = CellLayout::assemble(apart.parts.into_values().chain([part(
        "press1",
        "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\n",
    )]));
    m.handle(AgendaEvent::Layout(Arc::new(apart)), unix_ms());
    let proposal = m.handle(
        AgendaEvent::Request(transport(
            MessageType::ProposalReq,
            "p",
            "robot1.port",
            "press1.port",
        )),
        unix_ms(),
    );
    assert_eq!(
        reply(&proposal).info["detail"],
        "conveyor1 does not move parts from robot1.port to press1.port (as the cell's layout stands)"
    );
}
