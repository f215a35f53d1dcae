//! A conveyor's controller says when a move has left its origin (holarchy-xml's
//! `ROBOT_DEPARTED`), before the move's own reply: the controller client, against the
//! plant simulator over TCP, reports [`ControllerEvent::Departed`] and then the
//! command's [`ControllerEvent::Reply`]. A pallet that cannot leave (the track after its
//! stopper jammed) is not said to have left until it does. A departure naming no
//! command in flight is ignored, not a protocol error.

use std::path::Path;
use std::time::Duration;

use robot_bridge::client::ControllerEvent;
use schemas::TimeScale;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

mod common;
use common::plant::{
    control, control_line, loop_conveyor, move_to_buffer, one_conveyor_plant, start_plant,
};
use common::{reply, Harness};

fn plant_file(dir: &Path) -> std::path::PathBuf {
    one_conveyor_plant(dir, &loop_conveyor(2), "")
}

#[tokio::test(flavor = "multi_thread")]
async fn a_conveyor_move_is_said_departed_before_its_reply() {
    let dir = tempfile::tempdir().unwrap();
    let plant = start_plant(&plant_file(dir.path()), TimeScale::REAL).await;
    let mut h = Harness::start(
        plant.address("conveyor1").to_string(),
        Duration::from_secs(10),
    );
    h.wait_ready().await;
    h.commands.send(move_to_buffer(1, "p-1")).await.unwrap();
    assert_eq!(h.answer().await, ControllerEvent::Departed { id: 1 });
    // Said when the pallet left, not at the end: the part is still on its way.
    let view = control(&plant.control, "where").await;
    assert_eq!(view["in_transit"].as_array().unwrap().len(), 1, "{view:#}");
    assert_eq!(h.answer().await, reply(1, "arrived"));
    h.stop().await;
    plant.shutdown.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_pallet_that_cannot_leave_is_not_said_departed_until_it_does() {
    let dir = tempfile::tempdir().unwrap();
    let plant = start_plant(&plant_file(dir.path()), TimeScale::REAL).await;
    // The track from the loading point to the buffer is jammed: no pallet enters it.
    assert_eq!(
        control_line(&plant.control, "jam conveyor1.buf").await,
        "ok"
    );
    let mut h = Harness::start(
        plant.address("conveyor1").to_string(),
        Duration::from_secs(10),
    );
    h.wait_ready().await;
    h.commands.send(move_to_buffer(1, "p-1")).await.unwrap();
    // Longer than the whole move would take: still docked at the loading point.
    let quiet = tokio::time::timeout(Duration::from_millis(1500), h.answer()).await;
    assert!(quiet.is_err(), "{quiet:?}");
    let view = control(&plant.control, "where").await;
    let pallet = view["in_transit"][0]["load"]["carrier"].as_str().unwrap();
    assert_eq!(view["pallets"][pallet]["at"], "docked", "{view:#}");
    assert_eq!(
        control_line(&plant.control, "clear conveyor1.buf").await,
        "ok"
    );
    assert_eq!(h.answer().await, ControllerEvent::Departed { id: 1 });
    assert_eq!(h.answer().await, reply(1, "arrived"));
    h.stop().await;
    plant.shutdown.cancel();
}

/// A controller that says a departure of a command it was never sent, then answers the
/// command it was: the client goes on as if the stray message had not come.
#[tokio::test(flavor = "multi_thread")]
async fn a_departure_of_no_command_in_flight_is_ignored() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let controller = tokio::spawn(async move {
        let (mut link, _) = listener.accept().await.unwrap();
        link.write_all(b"<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>")
            .await
            .unwrap();
        let mut received = Vec::new();
        while !received.ends_with(b"</ROBOT_CMD>") {
            let mut buffer = [0u8; 1024];
            let n = link.read(&mut buffer).await.unwrap();
            assert!(n > 0, "the client closed");
            received.extend_from_slice(&buffer[..n]);
        }
        link.write_all(
            b"<ROBOT_DEPARTED><ID>99</ID></ROBOT_DEPARTED>\
              <ROBOT_DEPARTED><ID>1</ID></ROBOT_DEPARTED>\
              <ROBOT_DEPARTED><ID>1</ID></ROBOT_DEPARTED>\
              <ROBOT_REPLY><ID>1</ID><RESULT>arrived</RESULT></ROBOT_REPLY>\
              <ROBOT_DEPARTED><ID>1</ID></ROBOT_DEPARTED>",
        )
        .await
        .unwrap();
        // Held open until the client stops (a protocol error would have it close
        // sooner: a disconnect the test would see).
        let mut rest = [0u8; 64];
        if let Err(e) = link.read(&mut rest).await {
            eprintln!("the link: {e}");
        }
        received
    });
    let mut h = Harness::start(address, Duration::from_secs(10));
    h.wait_ready().await;
    h.commands.send(move_to_buffer(1, "p-1")).await.unwrap();
    // Told once, however often the controller says it; the strays go unreported.
    assert_eq!(h.answer().await, ControllerEvent::Departed { id: 1 });
    assert_eq!(h.answer().await, reply(1, "arrived"));
    let more = tokio::time::timeout(Duration::from_millis(300), h.next()).await;
    assert!(more.is_err(), "nothing more, no disconnect: {more:?}");
    h.stop().await;
    let received = controller.await.unwrap();
    assert!(
        String::from_utf8_lossy(&received).contains("<ID>1</ID>"),
        "{}",
        String::from_utf8_lossy(&received)
    );
}
