//! A conveyor's carriers out of service: homes granted only while fewer are held than
//! carriers are in service; the word journalled and restored.

use super::*;
use schemas::{unix_ms, CarrierWord};

/// conveyor1 with 4 pallets, a buffer of 3 and an entry.
fn conveyor_part() -> schemas::layout::LayoutPart {
    schemas::layout::part_from_toml(
        "conveyor1",
        "[[layout.locations]]\nname = \"load\"\nrole = \"entry_exit\"\ndock = \"conveyor1.load\"\n\n\
         [[layout.locations]]\nname = \"buffer\"\nrole = \"buffer\"\ncapacity = 3\ndock = \"conveyor1.b\"\n\n\
         [layout.conveyor]\nlength_mm = 2000\nspeed_mm_s = 1000\npallets = 4\n\
         stoppers = [{ name = \"load\", at_mm = 0 }, { name = \"b\", at_mm = 500 }, { name = \"s\", at_mm = 1000 }]\n",
    )
    .unwrap()
}

/// conveyor1's agenda, ready, with its part of the layout.
fn conveyor() -> AgendaMachine {
    let mut m = AgendaMachine::new(
        HolonId::resource("conveyor1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        unix_ms(),
    )
    .with_locations(Some(&conveyor_part()));
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m
}

fn home(order: &str) -> AgendaEvent {
    let info = json!({"part": order, "location": "conveyor1.buffer"});
    AgendaEvent::Request(
        Service::request(
            MessageType::BookingReq,
            schemas::PLACE_SERVICE,
            &format!("{order}/home"),
            HolonId::order(order).unwrap(),
        )
        .with_info(info.as_object().unwrap().clone()),
    )
}

fn word(carrier: &str, in_service: bool) -> AgendaEvent {
    AgendaEvent::CarrierWord {
        word: CarrierWord {
            carrier: carrier.into(),
            in_service,
        },
        by: "cell operator.default (user kim)".into(),
    }
}

fn answer(
    actions: &[AgendaAction],
) -> &Result<schemas::CarrierReply, (schemas::ErrorCode, String)> {
    actions
        .iter()
        .find_map(|a| match a {
            AgendaAction::CarrierAnswer(answer) => Some(answer),
            _ => None,
        })
        .expect("an answer")
}

fn granted(actions: &[AgendaAction]) {
    let r = reply(actions);
    assert_eq!(r.result, Some(true), "{r:?}");
}

#[test]
fn homes_are_granted_only_while_a_carrier_in_service_is_left_for_each() {
    let mut m = conveyor();
    // Two of four carriers out: two in service for the buffer's three homes.
    for carrier in ["p3", "conveyor1/p4"] {
        let out = m.handle(word(carrier, false), unix_ms());
        assert!(
            out.contains(&AgendaAction::StateChanged),
            "journalled: {out:?}"
        );
        assert!(answer(&out).is_ok(), "{out:?}");
    }
    assert_eq!(m.snapshot().carriers_out, ["p3", "p4"]);
    granted(&m.handle(home("o-1"), unix_ms()));
    granted(&m.handle(home("o-2"), unix_ms()));
    let refused = m.handle(home("o-3"), unix_ms());
    assert_refused(&refused, "no_place");
    let detail = reply(&refused).info["detail"].as_str().unwrap();
    assert!(
        detail.contains("2 of conveyor1's carriers in service") && detail.contains("p3, p4"),
        "{detail}"
    );
    // A part that has its home asks again (a lost reply): still its own.
    granted(&m.handle(home("o-2"), unix_ms()));

    // Said again: nothing changes, nothing to journal.
    let again = m.handle(word("p3", false), unix_ms());
    assert_eq!(again.len(), 1, "{again:?}");
    assert!(answer(&again).as_ref().unwrap().detail.contains("already"));

    // Across a restart, the word stands.
    let record = m.record();
    assert_eq!(record.carriers_out.len(), 2, "{record:?}");
    let mut m = AgendaMachine::restore(
        HolonId::resource("conveyor1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        record,
        Inheritance::Restarted,
        unix_ms(),
    )
    .with_locations(Some(&conveyor_part()));
    assert_eq!(m.snapshot().carriers_out, ["p3", "p4"]);
    assert_refused(&m.handle(home("o-3"), unix_ms()), "no_place");

    // One back: room for the third part.
    let back = m.handle(word("p3", true), unix_ms());
    let reply = answer(&back).as_ref().unwrap();
    assert_eq!(reply.out_of_service, ["p4"]);
    assert!(
        reply.detail.contains("3 of 4 carriers in service"),
        "{}",
        reply.detail
    );
    granted(&m.handle(home("o-3"), unix_ms()));
}

#[test]
fn a_word_on_a_carrier_the_conveyor_does_not_have_changes_nothing() {
    let mut m = conveyor();
    for carrier in ["p5", "p0", "pallet", "monorail/p1"] {
        let refused = m.handle(word(carrier, false), unix_ms());
        assert_eq!(refused.len(), 1, "{refused:?}");
        let (code, why) = answer(&refused).as_ref().unwrap_err();
        assert_eq!(*code, schemas::ErrorCode::Invalid);
        assert!(why.contains("p1 to p4"), "{why}");
    }
    assert!(m.record().carriers_out.is_empty());
    // A resource that is not a conveyor has no carriers.
    let mut station = manager();
    let (code, why) = answer(&station.handle(word("p1", false), unix_ms()))
        .as_ref()
        .unwrap_err()
        .clone();
    assert_eq!(code, schemas::ErrorCode::Invalid);
    assert!(why.contains("not a conveyor"), "{why}");
}
