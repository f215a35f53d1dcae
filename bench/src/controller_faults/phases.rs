//! The faults the campaign plays, one kind per phase, in rotation: robot-sim's flags
//! for each, and what the controller says in each (the words an operator must read).

/// One kind of fault: robot-sim's flags, and the words of the controller's that a step
/// failed by it must carry.
#[derive(Debug, Clone, Copy)]
pub struct FaultKind {
    /// Its name in the report.
    pub name: &'static str,
    /// robot-sim's flags (beside `--dialect`, `--delay-ms` and the count file).
    pub flags: &'static [&'static str],
}

/// The rotation: a clean phase first (the first job after a clean start), then every
/// fault robot-sim can play on a text dialect, one kind per phase. The "after" faults
/// happen once per robot-sim process: robot-sim is started again every `restart_s`.
pub const ROTATION: &[FaultKind] = &[
    FaultKind {
        name: "clean",
        flags: &[],
    },
    FaultKind {
        name: "fault-every",
        flags: &[
            "--fault-every",
            "7",
            "--fault-state",
            "fault",
            "--fault-for-ms",
            "1500",
        ],
    },
    FaultKind {
        name: "estop-every",
        flags: &[
            "--fault-every",
            "7",
            "--fault-state",
            "estop",
            "--fault-for-ms",
            "1500",
        ],
    },
    FaultKind {
        name: "unknown-state",
        flags: &["--unknown-state-every", "9", "--fault-for-ms", "2500"],
    },
    FaultKind {
        name: "error-every",
        flags: &["--error-every", "5"],
    },
    FaultKind {
        name: "garbage",
        flags: &["--garbage-after", "3"],
    },
    FaultKind {
        name: "close",
        flags: &["--close-after", "4"],
    },
    FaultKind {
        name: "reset",
        flags: &["--reset-after", "3"],
    },
    FaultKind {
        name: "wrong-id",
        flags: &["--wrong-id-after", "3"],
    },
    FaultKind {
        name: "hang",
        flags: &["--hang-after", "5"],
    },
    FaultKind {
        name: "estop-fragment-merge",
        flags: &[
            "--fault-every",
            "6",
            "--fault-state",
            "estop",
            "--fault-for-ms",
            "1000",
            "--fragment",
            "--merge",
        ],
    },
    FaultKind {
        name: "mixed",
        flags: &[
            "--error-every",
            "4",
            "--fault-every",
            "9",
            "--fault-for-ms",
            "1000",
            "--wrong-id-after",
            "5",
            "--fragment",
        ],
    },
];

/// What robot-sim logs when it plays a fault (a line of its stderr), by the name the
/// report counts it under.
pub const PLAYED: &[(&str, &str)] = &[
    ("fault", "reporting a fault"),
    ("unknown_state", "in a state the dialect does not describe"),
    ("garbage", "answering garbage"),
    ("close", "closing the connection (--close-after)"),
    ("reset", "resetting the connection halfway through"),
    ("wrong_id", "answering with another id"),
    ("hang", "not answering (--hang-after)"),
];

/// The reasons a step fails by, when the controller spoke, and the words of the
/// controller (robot-sim's, any of them) its detail must carry: its `END <id> FAIL
/// <reason>`, its `NAK <text>`, its `STATE ERROR <text>` or `STATE ESTOP`, the bytes it
/// sent that the dialect does not describe.
pub const SPOKEN: &[(&str, &[&str])] = &[
    (
        "controller_error",
        &[
            "simulated error (--error-every)",
            "unknown action",
            "refused:",
        ],
    ),
    (
        "controller_fault",
        &[
            "simulated fault (--fault-after)",
            "simulated emergency stop",
            "estop",
        ],
    ),
    ("controller_protocol_error", &["garbage", "HOMING"]),
];

/// Reasons of a step the controller did not speak to (it said nothing, or closed the
/// connection): the detail must say what happened, in the holon's words.
pub const UNSPOKEN: &[&str] = &["controller_timeout", "controller_disconnected"];

/// Reasons `--check` could have seen (a message the dialect cannot write for a job, a
/// result the step does not expect): never, after a dialect passed it.
pub const CHECKABLE: &[&str] = &["invalid_info", "unexpected_result"];
