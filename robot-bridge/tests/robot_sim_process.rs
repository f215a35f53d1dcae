//! `robot-sim` as a real process: the ready line, the protocol, the count file, SIGTERM.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn robot_sim_serves_counts_and_stops_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let counts = dir.path().join("counts.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_robot-sim"))
        .args(["--listen", "127.0.0.1:0", "--count-file"])
        .arg(&counts)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.path().join("sim.log")).unwrap())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    let address = line
        .trim()
        .strip_prefix("listening on ")
        .expect(&line)
        .to_string();

    let mut socket = TcpStream::connect(&address).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    socket
        .write_all(b"<?xml version=\"1.0\"?><ROBOT_CMD><ID>42</ID><ACTION>pick</ACTION><POS X=\"100.0\" Y=\"20.0\" Z=\"5.0\" A=\"0.0\" B=\"0.0\" C=\"0.0\"></POS></ROBOT_CMD>")
        .unwrap();
    let expected = "<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS><ROBOT_REPLY><ID>42</ID><RESULT>picking_done</RESULT></ROBOT_REPLY>";
    let mut got = vec![0u8; expected.len()];
    socket.read_exact(&mut got).unwrap();
    assert_eq!(String::from_utf8(got).unwrap(), expected);

    // The count file follows the reply (written off the command's path), shortly.
    let read = || -> serde_json::Value {
        std::fs::read_to_string(&counts)
            .ok()
            .and_then(|text| serde_json::from_str(&text).ok())
            .unwrap_or_default()
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(2);
    while read()["executed"] != 1 && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(1));
    }
    let json = read();
    assert_eq!(json["executed"], 1);
    assert_eq!(json["by_action"]["pick"], 1);
    assert_eq!(json["aborted"], 0);

    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "{status}");
    // Stopped, it left its last counts on disk.
    assert_eq!(read()["executed"], 1);
    assert_eq!(read()["received"], 1);
    let mut rest = String::new();
    stdout.read_to_string(&mut rest).unwrap();
    assert_eq!(rest.trim(), "executed 1 commands");
    // Its log, redirected to a file, is plain text: no terminal colour codes.
    let log = std::fs::read_to_string(dir.path().join("sim.log")).unwrap();
    assert!(!log.is_empty(), "robot-sim logged nothing");
    assert!(
        !log.contains('\u{1b}'),
        "colour codes in a log file: {log:?}"
    );
}

#[test]
fn robot_sim_fenced_needs_a_dialect_that_can_fence() {
    let out = Command::new(env!("CARGO_BIN_EXE_robot-sim"))
        .args(["--fenced", "--dialect", "kuka-eki", "--check"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("cannot fence"), "{stderr}");
    let out = Command::new(env!("CARGO_BIN_EXE_robot-sim"))
        .args(["--fenced", "--check"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = Command::new(env!("CARGO_BIN_EXE_robot-sim"))
        .arg("--help")
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(
        help.contains("--fenced") && help.contains("--lease-ms"),
        "{help}"
    );
}
