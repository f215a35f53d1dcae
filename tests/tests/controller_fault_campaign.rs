//! Issue 41's "Done when", briefly: the controller fault campaign (`bench
//! controller-faults`) through the real binaries, every phase a few seconds: a resource
//! on the job-ack-end dialect (docs/dialects.md, section 7.7) kept busy with orders
//! while robot-sim plays each fault it can, restarted within every phase. The campaign
//! checks that nothing was written to a stopped controller, that reconnects kept the
//! backoff, that every failed step's reason carries the controller's words, that every
//! order ended, and that the first job after the clean start was done; it exits
//! non-zero on any miss. The hour run is in docs/benchmarks.md, "Controller faults".

use std::process::Command;

use holarchy_tests::*;

#[tokio::test(flavor = "multi_thread")]
async fn every_fault_robot_sim_plays_keeps_the_controller_rules_briefly() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("campaign.json");
    let dialect = workspace_root().join("deploy/dialects/examples/job-ack-end.toml");
    // Twelve phases of 4 s (each kind of fault once), robot-sim restarted every 4 s.
    let run = Command::new(bin("bench"))
        .args(["controller-faults", "--minutes", "0.8", "--phase-s", "4"])
        .args(["--restart-s", "4", "--in-flight", "3", "--dialect"])
        .arg(&dialect)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&run.stdout);
    println!("{said}\n{}", String::from_utf8_lossy(&run.stderr));
    assert!(
        run.status.success(),
        "the campaign found violations: {said}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(summary["violations"], serde_json::json!([]), "{summary}");
    let totals = &summary["totals"];
    assert_eq!(totals["refused_while_stopped"], 0, "{totals}");
    // The faults were played, not just scheduled: the ones that come after a few
    // commands at most (each phase runs dozens).
    for kind in ["garbage", "close", "reset", "wrong_id", "hang"] {
        assert!(
            totals["played"][kind].as_u64().unwrap_or(0) > 0,
            "{kind} never played: {totals}"
        );
    }
    // Every phase, the clean one and the drain included.
    assert_eq!(summary["phases"].as_array().unwrap().len(), 13, "{summary}");
    assert!(summary["orders"]["by_status"]["done"].as_u64().unwrap_or(0) > 0);
    // The CSV beside it, a row per phase.
    let csv = std::fs::read_to_string(out.with_extension("csv")).unwrap();
    assert_eq!(csv.lines().count(), 14, "{csv}");
}
