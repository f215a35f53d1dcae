use super::*;
use AttemptAction as A;
use AttemptEvent as E;

fn robot(n: u32) -> HolonId {
    HolonId::resource(&format!("robot{n}")).unwrap()
}

fn timing() -> AttemptTiming {
    AttemptTiming {
        retry_interval: Duration::from_millis(100),
        retry_max: Duration::from_millis(400),
        idle_poll: Duration::from_secs(10),
        no_resource_timeout: Duration::from_secs(60),
        step_timeout: Duration::from_secs(30),
    }
}

fn attempt(phase: Phase) -> (Attempt, Instant) {
    let now = Instant::now();
    (Attempt::new(phase, timing(), now), now)
}

fn later(now: Instant) -> Instant {
    now + Duration::from_secs(61)
}

#[test]
fn proposing_asks_for_proposals_when_it_begins_and_when_woken() {
    let (mut a, now) = attempt(Phase::Proposing);
    assert_eq!(a.handle(E::Resumed, now), vec![A::AskProposals]);
    assert_eq!(a.handle(E::Woken, now), vec![A::AskProposals]);
    assert_eq!(a.phase(), &Phase::Proposing);
}

#[test]
fn proposals_book_the_best_first() {
    let (mut a, now) = attempt(Phase::Proposing);
    let actions = a.handle(E::Proposals(vec![robot(1), robot(2)]), now);
    assert_eq!(
        actions,
        vec![A::Record(Phase::Booking(robot(1))), A::AskBooking(robot(1))]
    );
    assert_eq!(a.phase(), &Phase::Booking(robot(1)));
}

#[test]
fn no_proposal_waits_idle_until_give_up_then_ends_with_no_resource() {
    let (mut a, now) = attempt(Phase::Proposing);
    let actions = a.handle(E::Proposals(vec![]), now);
    assert_eq!(
        actions,
        vec![A::Wait {
            pause: Duration::from_secs(10),
            idle: true,
            until: now + Duration::from_secs(60)
        }]
    );
    assert_eq!(
        a.handle(E::Proposals(vec![]), later(now)),
        vec![A::End(StepOutcome::NoResource)]
    );
}

#[test]
fn an_accepted_booking_is_recorded_published_and_started() {
    let (mut a, now) = attempt(Phase::Proposing);
    a.handle(E::Proposals(vec![robot(1)]), now);
    let actions = a.handle(E::BookingAnswer(Answer::Accepted), now);
    assert_eq!(
        actions,
        vec![
            A::Record(Phase::Booked(robot(1))),
            A::Publish,
            A::AskStart(robot(1))
        ]
    );
}

#[test]
fn a_refused_booking_tries_the_next_candidate_then_waits_with_a_growing_pause() {
    let (mut a, now) = attempt(Phase::Proposing);
    a.handle(E::Proposals(vec![robot(1), robot(2)]), now);
    assert_eq!(
        a.handle(
            E::BookingAnswer(Answer::Refused(Some(Reason::AgendaFull))),
            now
        ),
        vec![A::Record(Phase::Booking(robot(2))), A::AskBooking(robot(2))]
    );
    let wait = |pause| {
        vec![
            A::Record(Phase::Proposing),
            A::Wait {
                pause,
                idle: false,
                until: now + Duration::from_secs(60),
            },
        ]
    };
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Silent), now),
        wait(Duration::from_millis(100))
    );
    assert_eq!(a.handle(E::Woken, now), vec![A::AskProposals]);
    a.handle(E::Proposals(vec![robot(1)]), now);
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Silent), now),
        wait(Duration::from_millis(200)),
        "the pause doubles"
    );
    a.handle(E::Proposals(vec![robot(1)]), now);
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Silent), later(now)),
        vec![A::Record(Phase::Proposing), A::End(StepOutcome::NoResource)]
    );
}

#[test]
fn a_resumed_booking_is_asked_again_and_if_refused_a_new_round_starts_at_once() {
    let (mut a, now) = attempt(Phase::Booking(robot(3)));
    assert_eq!(a.handle(E::Resumed, now), vec![A::AskBooking(robot(3))]);
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Refused(None)), now),
        vec![A::Record(Phase::Proposing), A::AskProposals]
    );
}

#[test]
fn a_started_step_is_recorded_published_and_watched_for_the_step_timeout() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    assert_eq!(a.handle(E::Resumed, now), vec![A::AskStart(robot(1))]);
    assert_eq!(
        a.handle(E::StartAnswer(Answer::Accepted), now),
        vec![
            A::Record(Phase::Started(robot(1))),
            A::Publish,
            A::Watch {
                provider: robot(1),
                pause: Duration::from_secs(30),
                started: true,
                may_run: true,
            }
        ]
    );
    let done = StepOutcome::Done {
        provider: robot(1),
        results: Default::default(),
    };
    assert_eq!(
        a.handle(E::Watched(Some(done.clone())), now),
        vec![A::End(done)]
    );
}

#[test]
fn busy_silent_or_unavailable_waits_for_the_turn_and_asks_again() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    let watch = |ms| {
        vec![A::Watch {
            provider: robot(1),
            pause: Duration::from_millis(ms),
            started: false,
            may_run: false,
        }]
    };
    assert_eq!(
        a.handle(E::StartAnswer(Answer::Refused(Some(Reason::Busy))), now),
        watch(100)
    );
    assert_eq!(a.handle(E::Watched(None), now), vec![A::AskStart(robot(1))]);
    assert_eq!(a.handle(E::StartAnswer(Answer::Silent), now), watch(200));
    assert_eq!(
        a.handle(
            E::StartAnswer(Answer::Refused(Some(Reason::Unavailable))),
            now
        ),
        watch(400)
    );
    assert_eq!(a.phase(), &Phase::Booked(robot(1)));
}

#[test]
fn unavailable_past_give_up_cancels_and_fails() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    assert_eq!(
        a.handle(
            E::StartAnswer(Answer::Refused(Some(Reason::Unavailable))),
            later(now)
        ),
        vec![
            A::CancelBooking(robot(1)),
            A::End(StepOutcome::Failed {
                provider: robot(1),
                reason: "start refused: unavailable".into(),
                detail: None,
            })
        ]
    );
}

#[test]
fn a_start_refused_without_a_reason_cancels_and_fails() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    assert_eq!(
        a.handle(E::StartAnswer(Answer::Refused(None)), now),
        vec![
            A::CancelBooking(robot(1)),
            A::End(StepOutcome::Failed {
                provider: robot(1),
                reason: "start refused: refused".into(),
                detail: None,
            })
        ]
    );
}

#[test]
fn not_booked_means_the_booking_was_lost() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    assert_eq!(
        a.handle(
            E::StartAnswer(Answer::Refused(Some(Reason::NotBooked))),
            now
        ),
        vec![A::AskOutcome(robot(1))]
    );
    // Nobody can tell what became of it: lost.
    assert_eq!(
        a.handle(E::Outcome(None), now),
        vec![A::End(StepOutcome::Lost {
            provider: robot(1),
            why: "the booking was lost".into()
        })]
    );
}

#[test]
fn a_resource_lost_while_booked_gets_its_booking_cancelled_when_back() {
    let (mut a, now) = attempt(Phase::Booked(robot(1)));
    let lost = StepOutcome::Lost {
        provider: robot(1),
        why: "the resource vanished".into(),
    };
    assert_eq!(
        a.handle(E::Watched(Some(lost.clone())), now),
        vec![A::CancelWhenBack(robot(1)), A::End(lost)]
    );
}

#[test]
fn a_started_step_without_a_result_in_time_fails() {
    let (mut a, now) = attempt(Phase::Started(robot(2)));
    // Resumed (a restart, a takeover of the node): the resource is asked first;
    // nobody can tell, so what is left of the step timeout is watched.
    assert_eq!(a.handle(E::Resumed, now), vec![A::AskOutcome(robot(2))]);
    assert_eq!(
        a.handle(E::Outcome(None), now),
        vec![A::Watch {
            provider: robot(2),
            pause: Duration::from_secs(30),
            started: true,
            may_run: true,
        }]
    );
    assert_eq!(
        a.handle(E::Watched(None), now),
        vec![A::AskOutcome(robot(2))]
    );
    // Nobody can tell what became of it: failed, as before asking.
    assert_eq!(
        a.handle(E::Outcome(None), now + Duration::from_secs(30)),
        vec![A::End(StepOutcome::Failed {
            provider: robot(2),
            reason: "no result within 30s".into(),
            detail: None,
        })]
    );
}

#[test]
fn an_event_the_phase_does_not_expect_changes_nothing() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    assert_eq!(a.handle(E::Proposals(vec![robot(2)]), now), vec![]);
    assert_eq!(a.handle(E::BookingAnswer(Answer::Accepted), now), vec![]);
    assert_eq!(a.phase(), &Phase::Started(robot(1)));
}

fn on_turn(phase: Phase) -> (Attempt, Instant) {
    let now = Instant::now();
    (
        Attempt::new(phase, timing(), now).starting_on_turn(true),
        now,
    )
}

#[test]
fn a_booking_that_started_on_its_turn_is_recorded_started_and_watched() {
    let (mut a, now) = on_turn(Phase::Booking(robot(1)));
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Started), now),
        vec![
            A::Record(Phase::Started(robot(1))),
            A::Publish,
            A::Watch {
                provider: robot(1),
                pause: Duration::from_secs(30),
                started: true,
                may_run: true,
            }
        ]
    );
}

#[test]
fn a_booking_on_turn_that_waits_is_watched_with_the_grace_of_a_running_step() {
    let (mut a, now) = on_turn(Phase::Booking(robot(1)));
    let watch = A::Watch {
        provider: robot(1),
        pause: Duration::from_millis(100),
        started: false,
        may_run: true,
    };
    // No start is sent: the resource starts it on its turn and says so.
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Accepted), now),
        vec![
            A::Record(Phase::Booked(robot(1))),
            A::Publish,
            watch.clone()
        ]
    );
    // A pause without news: the order asks (a publication may have been missed).
    assert_eq!(a.handle(E::Watched(None), now), vec![A::AskStart(robot(1))]);
    assert_eq!(
        a.handle(E::StartAnswer(Answer::Refused(Some(Reason::Busy))), now),
        vec![A::Watch {
            provider: robot(1),
            pause: Duration::from_millis(200),
            started: false,
            may_run: true,
        }]
    );
    // The resource publishes that the step runs: started, without a start.
    assert_eq!(
        a.handle(E::Began, now),
        vec![
            A::Record(Phase::Started(robot(1))),
            A::Publish,
            A::Watch {
                provider: robot(1),
                pause: Duration::from_secs(30),
                started: true,
                may_run: true,
            }
        ]
    );
    // Began means nothing once started, or before booking.
    assert_eq!(a.handle(E::Began, now), vec![]);
    let (mut proposing, now) = on_turn(Phase::Proposing);
    assert_eq!(proposing.handle(E::Began, now), vec![]);
}

#[test]
fn a_booking_asked_to_start_by_request_asks_start_at_once() {
    let (mut a, now) = attempt(Phase::Booking(robot(1)));
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Accepted), now),
        vec![
            A::Record(Phase::Booked(robot(1))),
            A::Publish,
            A::AskStart(robot(1))
        ]
    );
}

#[test]
fn silence_after_asking_to_start_on_turn_never_books_elsewhere() {
    // The job may have begun: ask that resource, never the next candidate.
    let (mut a, now) = on_turn(Phase::Proposing);
    a.handle(E::Proposals(vec![robot(1), robot(2)]), now);
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Silent), now),
        vec![A::Record(Phase::Booked(robot(1))), A::AskStart(robot(1))]
    );
    // The booking never arrived: lost, and a new attempt (a new conversation).
    assert_eq!(
        a.handle(
            E::StartAnswer(Answer::Refused(Some(Reason::NotBooked))),
            now
        ),
        vec![A::AskOutcome(robot(1))]
    );
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::NeverReached))), now),
        vec![A::End(StepOutcome::Lost {
            provider: robot(1),
            why: "the step never reached the controller".into()
        })]
    );
    let (mut a, now) = on_turn(Phase::Booked(robot(1)));
    a.handle(
        E::StartAnswer(Answer::Refused(Some(Reason::NotBooked))),
        now,
    );
    assert_eq!(
        a.handle(E::Outcome(None), now),
        vec![A::End(StepOutcome::Lost {
            provider: robot(1),
            why: "the booking was lost".into()
        })]
    );
    // Without start on turn, silence moves on to the next candidate.
    let (mut a, now) = attempt(Phase::Proposing);
    a.handle(E::Proposals(vec![robot(1), robot(2)]), now);
    assert_eq!(
        a.handle(E::BookingAnswer(Answer::Silent), now),
        vec![A::Record(Phase::Booking(robot(2))), A::AskBooking(robot(2))]
    );
}

/// What robot`n` says of the conversation.
fn told(n: u32, outcome: Outcome) -> OutcomeReply {
    schemas::OutcomeRequest::new("o/1/1", "pick_n_place", HolonId::order("o").unwrap())
        .answer(&robot(n), outcome)
}

fn watch(n: u32, pause: Duration) -> AttemptAction {
    A::Watch {
        provider: robot(n),
        pause,
        started: true,
        may_run: true,
    }
}

#[test]
fn a_provider_that_came_back_is_asked_and_a_done_it_tells_ends_the_step_done() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Resumed, now);
    assert_eq!(a.handle(E::CameBack, now), vec![A::AskOutcome(robot(1))]);
    let mut done = told(1, Outcome::Done);
    done.results.insert("pick".into(), "picking_done".into());
    assert_eq!(
        a.handle(E::Outcome(Some(done.clone())), now),
        vec![A::End(StepOutcome::Done {
            provider: robot(1),
            results: done.results
        })]
    );
}

#[test]
fn a_provider_that_came_back_and_cannot_tell_is_watched_for_what_is_left_of_the_timeout() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Resumed, now);
    a.handle(E::CameBack, now);
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::Unknown))), now),
        vec![watch(1, Duration::from_secs(30))]
    );
    let later = now + Duration::from_secs(10);
    a.handle(E::CameBack, later);
    assert_eq!(
        a.handle(E::Outcome(None), later),
        vec![watch(1, Duration::from_secs(20))]
    );
    assert_eq!(a.phase(), &Phase::Started(robot(1)));
    // Back once more, past the step timeout, and still nobody can tell: failed.
    let past = now + Duration::from_secs(31);
    a.handle(E::CameBack, past);
    assert_eq!(
        a.handle(E::Outcome(None), past),
        vec![A::End(StepOutcome::Failed {
            provider: robot(1),
            reason: "no result within 30s".into(),
            detail: None,
        })]
    );
}

#[test]
fn a_step_its_resource_runs_itself_is_watched_for_the_step_timeout_not_polled() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Resumed, now);
    let later = now + Duration::from_secs(10);
    a.handle(E::CameBack, later);
    let mut running = told(1, Outcome::Running);
    running.source = OutcomeSource::Journal;
    assert_eq!(
        a.handle(E::Outcome(Some(running.clone())), later),
        vec![watch(1, Duration::from_secs(20))]
    );
    // Past the step timeout, a step still running there is polled.
    let past = now + Duration::from_secs(31);
    a.handle(E::Watched(None), past);
    assert_eq!(
        a.handle(E::Outcome(Some(running)), past),
        vec![watch(1, Duration::from_millis(400))]
    );
}

#[test]
fn a_poll_of_a_running_step_that_goes_unanswered_waits_out_the_step_timeout() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Resumed, now);
    a.handle(E::CameBack, now);
    a.handle(E::Outcome(Some(told(1, Outcome::Running))), now);
    let poll = now + Duration::from_millis(400);
    assert_eq!(
        a.handle(E::Watched(None), poll),
        vec![A::AskOutcome(robot(1))]
    );
    assert_eq!(
        a.handle(E::Outcome(None), poll),
        vec![watch(1, Duration::from_millis(29_600))]
    );
}

#[test]
fn after_the_step_timeout_the_outcome_told_ends_the_step() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Watched(None), now);
    let mut failed = told(1, Outcome::Failed);
    failed.reason = Some(Reason::Interrupted);
    assert_eq!(
        a.handle(E::Outcome(Some(failed)), now),
        vec![A::End(StepOutcome::Failed {
            provider: robot(1),
            reason: "interrupted".into(),
            detail: None,
        })]
    );
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Watched(None), now);
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::NeverReached))), now),
        vec![A::End(StepOutcome::Lost {
            provider: robot(1),
            why: "the step never reached the controller".into()
        })]
    );
}

#[test]
fn a_step_told_running_is_polled_until_it_ends() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::CameBack, now);
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::Running))), now),
        vec![watch(1, Duration::from_millis(400))]
    );
    assert_eq!(
        a.handle(E::Watched(None), now),
        vec![A::AskOutcome(robot(1))]
    );
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::Done))), now),
        vec![A::End(StepOutcome::Done {
            provider: robot(1),
            results: Default::default()
        })]
    );
}

#[test]
fn a_booking_not_booked_but_running_on_the_controller_is_started() {
    let (mut a, now) = on_turn(Phase::Booked(robot(1)));
    a.handle(
        E::StartAnswer(Answer::Refused(Some(Reason::NotBooked))),
        now,
    );
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::Running))), now),
        vec![
            A::Record(Phase::Started(robot(1))),
            A::Publish,
            watch(1, Duration::from_millis(400))
        ]
    );
    assert_eq!(a.phase(), &Phase::Started(robot(1)));
}

#[test]
fn an_outcome_nobody_asked_for_changes_nothing() {
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::Done))), now),
        vec![]
    );
    let (mut b, now) = attempt(Phase::Booked(robot(1)));
    assert_eq!(b.handle(E::CameBack, now), vec![]);
    assert_eq!(b.handle(E::Outcome(None), now), vec![]);
}

#[test]
fn an_interrupted_step_is_asked_and_ends_as_the_controller_says() {
    let interrupted = StepOutcome::Failed {
        provider: robot(1),
        reason: "interrupted".into(),
        detail: None,
    };
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    assert_eq!(
        a.handle(E::Watched(Some(interrupted.clone())), now),
        vec![A::AskOutcome(robot(1))]
    );
    let mut done = told(1, Outcome::Done);
    done.source = OutcomeSource::Controller;
    done.results.insert("place".into(), "placing_done".into());
    assert_eq!(
        a.handle(E::Outcome(Some(done.clone())), now),
        vec![A::End(StepOutcome::Done {
            provider: robot(1),
            results: done.results
        })]
    );
    // Nobody can tell: interrupted, as reported.
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Watched(Some(interrupted.clone())), now);
    assert_eq!(
        a.handle(E::Outcome(None), now),
        vec![A::End(interrupted.clone())]
    );
    // Nothing reached the controller: booked again, not a failure.
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    a.handle(E::Watched(Some(interrupted)), now);
    assert_eq!(
        a.handle(E::Outcome(Some(told(1, Outcome::NeverReached))), now),
        vec![A::End(StepOutcome::Lost {
            provider: robot(1),
            why: "the step never reached the controller".into()
        })]
    );
    // Any other failure ends the step at once.
    let (mut a, now) = attempt(Phase::Started(robot(1)));
    let fault = StepOutcome::Failed {
        provider: robot(1),
        reason: "controller_fault".into(),
        detail: None,
    };
    assert_eq!(
        a.handle(E::Watched(Some(fault.clone())), now),
        vec![A::End(fault)]
    );
}
