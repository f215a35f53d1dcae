use super::*;

#[test]
fn states_are_numbered_as_isa_tr88_2022_and_opc_30050() {
    let expected = [
        (0, "Undefined"),
        (1, "Clearing"),
        (2, "Stopped"),
        (3, "Starting"),
        (4, "Idle"),
        (5, "Suspended"),
        (6, "Execute"),
        (7, "Stopping"),
        (8, "Aborting"),
        (9, "Aborted"),
        (10, "Holding"),
        (11, "Held"),
        (12, "Unholding"),
        (13, "Suspending"),
        (14, "Unsuspending"),
        (15, "Resetting"),
        (16, "Completing"),
        (17, "Complete"),
    ];
    for (number, name) in expected {
        let state = PackmlState::from_number(number).unwrap();
        assert_eq!(state.name(), name);
        assert_eq!(state.number(), number);
    }
    assert_eq!(PackmlState::from_number(18), None);
    assert_eq!(PackmlState::from_number(-1), None);
}

#[test]
fn commands_and_modes_are_numbered_as_packtags() {
    let names: Vec<_> = PackmlCommand::ALL
        .iter()
        .map(|c| (c.number(), c.name()))
        .collect();
    assert_eq!(
        names,
        [
            (1, "Reset"),
            (2, "Start"),
            (3, "Stop"),
            (4, "Hold"),
            (5, "Unhold"),
            (6, "Suspend"),
            (7, "Unsuspend"),
            (8, "Abort"),
            (9, "Clear"),
            (10, "Complete")
        ]
    );
    assert_eq!("hold".parse::<PackmlCommand>(), Ok(PackmlCommand::Hold));
    assert_eq!("8".parse::<PackmlCommand>(), Ok(PackmlCommand::Abort));
    assert!("11".parse::<PackmlCommand>().is_err());
    assert!("halt".parse::<PackmlCommand>().is_err());
    assert_eq!(UnitMode::from_number(2), Some(UnitMode::Maintenance));
    assert_eq!("manual".parse::<UnitMode>(), Ok(UnitMode::Manual));
    assert!("0".parse::<UnitMode>().is_err());
}

#[test]
fn stop_is_accepted_everywhere_but_five_states() {
    for state in PackmlState::ALL {
        let refused = matches!(
            state,
            PackmlState::Stopping
                | PackmlState::Stopped
                | PackmlState::Clearing
                | PackmlState::Aborting
                | PackmlState::Aborted
        );
        assert_eq!(
            state.accepts(PackmlCommand::Stop).is_err(),
            refused,
            "{state}"
        );
    }
}

#[test]
fn abort_is_accepted_everywhere_but_aborting_and_aborted() {
    for state in PackmlState::ALL {
        let refused = matches!(state, PackmlState::Aborting | PackmlState::Aborted);
        assert_eq!(
            state.accepts(PackmlCommand::Abort),
            if refused {
                Err(Refusal::NotInState {
                    command: PackmlCommand::Abort,
                    state,
                })
            } else {
                Ok(PackmlState::Aborting)
            },
            "{state}"
        );
    }
}

#[test]
fn each_row_of_the_table_leads_through_its_acting_state() {
    use PackmlCommand as C;
    use PackmlState as S;
    let rows = [
        (S::Stopped, C::Reset, S::Resetting, S::Idle),
        (S::Complete, C::Reset, S::Resetting, S::Idle),
        (S::Idle, C::Start, S::Starting, S::Execute),
        (S::Execute, C::Hold, S::Holding, S::Held),
        (S::Suspended, C::Hold, S::Holding, S::Held),
        (S::Held, C::Unhold, S::Unholding, S::Execute),
        (S::Execute, C::Suspend, S::Suspending, S::Suspended),
        (S::Suspended, C::Unsuspend, S::Unsuspending, S::Execute),
        (S::Execute, C::Stop, S::Stopping, S::Stopped),
        (S::Held, C::Abort, S::Aborting, S::Aborted),
        (S::Aborted, C::Clear, S::Clearing, S::Stopped),
    ];
    for (from, command, acting, wait) in rows {
        assert_eq!(from.accepts(command), Ok(acting), "{from} {command}");
        assert!(acting.is_acting());
        assert_eq!(acting.completes_to(), Some(wait));
        assert!(!wait.is_acting() || wait == S::Execute);
    }
}

#[test]
fn a_command_out_of_place_is_refused_naming_the_state() {
    let refusal = PackmlState::Execute
        .accepts(PackmlCommand::Unhold)
        .unwrap_err();
    assert_eq!(refusal.to_string(), "Unhold is not allowed in Execute");
    assert_eq!(
        PackmlState::Execute.accepts(PackmlCommand::Complete),
        Err(Refusal::NotSupported {
            command: PackmlCommand::Complete
        })
    );
    assert_eq!(
        PackmlState::Execute.commands(),
        [
            PackmlCommand::Stop,
            PackmlCommand::Hold,
            PackmlCommand::Suspend,
            PackmlCommand::Abort
        ]
    );
    assert_eq!(PackmlState::Aborted.commands(), [PackmlCommand::Clear]);
}

#[test]
fn the_mode_changes_only_in_stopped_idle_or_aborted() {
    let allowed: Vec<_> = PackmlState::ALL
        .into_iter()
        .filter(|s| s.allows_mode_change())
        .collect();
    assert_eq!(
        allowed,
        [
            PackmlState::Stopped,
            PackmlState::Idle,
            PackmlState::Aborted
        ]
    );
}

#[test]
fn requests_and_replies_read_as_json() {
    let request = PackmlRequest::from_json(br#"{"command":"hold","by":"op"}"#).unwrap();
    assert_eq!(request, PackmlRequest::command(PackmlCommand::Hold, "op"));
    let request = PackmlRequest::from_json(br#"{"mode":"maintenance"}"#).unwrap();
    assert_eq!(request.mode, Some(UnitMode::Maintenance));
    for bad in [
        &br#"{"command":"halt"}"#[..],
        br#"{}"#,
        br#"{"command":"hold","mode":"manual"}"#,
        br#"{"command":"hold","extra":1}"#,
        b"not json",
    ] {
        assert!(PackmlRequest::from_json(bad).is_err(), "{bad:?}");
    }
    let reply = PackmlReply {
        job: None,
        state: PackmlState::Execute,
        state_number: 6,
        mode: UnitMode::Production,
        refused: Some(Refusal::NotInState {
            command: PackmlCommand::Unhold,
            state: PackmlState::Execute,
        }),
        detail: None,
    };
    let text = serde_json::to_string(&reply).unwrap();
    assert!(text.contains(r#""refusal":"not_in_state""#), "{text}");
    assert_eq!(serde_json::from_str::<PackmlReply>(&text).unwrap(), reply);
}
