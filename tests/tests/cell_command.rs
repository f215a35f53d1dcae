//! The operator's command, as a user runs it.

use std::process::Command;

use holarchy_tests::*;
use schemas::HolonId;

#[test]
fn order_node_and_holon_node_check_their_configs() {
    for (program, config) in [
        ("order-node", "orders1.toml"),
        ("holon-node", "robot1.toml"),
    ] {
        let output = Command::new(bin(program))
            .arg("--config")
            .arg(demo_config(config))
            .arg("--check")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(output.status.success(), "{program}: {stdout}");
        assert!(stdout.contains(": ok ("), "{program}: {stdout}");
    }
    let bad = Command::new(bin("order-node"))
        .arg("--config")
        .arg(demo_config("orders1.toml"))
        .args(["--name", "Bad Name", "--check"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    // A standby shares its orders through etcd: without it, it would be a twin.
    let twin = Command::new(bin("order-node"))
        .arg("--config")
        .arg(demo_config("orders1.toml"))
        .args(["--standby", "--check"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&twin.stderr);
    assert!(!twin.status.success(), "{said}");
    assert!(said.contains("--standby needs [journal] etcd"), "{said}");
}

#[test]
fn a_holon_is_a_client_of_its_router_and_says_what_a_client_cannot_do() {
    let check = |extra: &[&str]| {
        let output = Command::new(bin("holon-node"))
            .arg("--config")
            .arg(demo_config("robot1.toml"))
            .args(extra)
            .arg("--check")
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
        (output.status.success(), text)
    };
    // A client listens on nothing: asked to, it refuses and says why and what to do.
    let (ok, text) = check(&["--listen", "tcp/127.0.0.1:0"]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("listens on nothing") && text.contains("peer"),
        "{text}"
    );
    // A peer may listen.
    let (ok, text) = check(&["--mode", "peer", "--listen", "tcp/127.0.0.1:0"]);
    assert!(ok, "{text}");
    // A mode that is not one is refused by the command line.
    let (ok, text) = check(&["--mode", "router"]);
    assert!(!ok && text.contains("--mode"), "{text}");
}

#[test]
fn cell_demo_completes_every_order_and_hot_adds_a_robot() {
    let output = Command::new(bin("cell"))
        .args([
            "demo",
            "--orders",
            "6",
            "--delay-ms",
            "60",
            "--cell",
            "t-demo",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("submitted 6 orders of breaker"), "{stdout}");
    assert!(stdout.contains("+ hot-added resource/robot3"), "{stdout}");
    // Every order that passed shows its last step (the inspection) before `Done`.
    for line in stdout.lines().filter(|l| l.trim_end().ends_with(" Done")) {
        let order = line.split_whitespace().nth(1).unwrap();
        assert!(
            stdout
                .lines()
                .any(|l| l.split_whitespace().nth(1) == Some(order)
                    && l.contains(" inspect ")
                    && l.contains("done by")),
            "{order}'s passing inspection is not shown: {stdout}"
        );
    }
    assert!(stdout.contains("orders failed   0"), "{stdout}");
    assert!(stdout.contains("resource/conveyor1"), "{stdout}");
    assert!(
        stdout.contains("stopping everything the demo started"),
        "{stdout}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn cell_status_lists_the_live_holons() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-status").await.unwrap();
    let sim = Sim::start(dir.path(), "sim", "127.0.0.1:0", &[]).unwrap();
    let config = resource_config(dir.path(), "robot7", 5000).unwrap();
    let _node = start_node(
        dir.path(),
        &config,
        "t-status",
        &cell.endpoint,
        &sim.address,
        &[],
    )
    .unwrap();
    cell.wait_alive(&HolonId::resource("robot7").unwrap())
        .await
        .unwrap();
    cell.wait_state("robot7", "free", |s| s["state"] == "free")
        .await
        .unwrap();
    let _orders = cell.start_order_node(dir.path(), &[]).await.unwrap();
    let output = tokio::process::Command::new(bin("cell"))
        .args(["status", "--cell", "t-status", "--connect", &cell.endpoint])
        .output()
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}");
    assert!(stdout.contains("cell t-status: 1 live holon"), "{stdout}");
    let line = stdout
        .lines()
        .find(|l| l.starts_with("resource/robot7"))
        .unwrap_or_else(|| panic!("{stdout}"));
    let columns: Vec<&str> = line.split_whitespace().collect();
    assert_eq!(
        columns,
        [
            "resource/robot7",
            "resource",
            "free",
            "Execute(6)",
            "ready",
            "0",
            "0",
            concat!(env!("CARGO_PKG_VERSION"), "/v1")
        ]
    );
    // Order-nodes are listed with their orders' counts.
    let line = stdout
        .lines()
        .find(|l| l.starts_with("orders1 "))
        .unwrap_or_else(|| panic!("no order-node line: {stdout}"));
    assert_eq!(
        line.split_whitespace().collect::<Vec<_>>(),
        ["orders1", "0", "0", "0"]
    );
}

/// A secure cell's endpoint reached without its PKI: the tool says what is missing
/// instead of timing out.
#[test]
fn a_tls_endpoint_without_a_pki_says_so() {
    for command in [
        &["status"][..],
        &["submit", "breaker"],
        &["packml", "robot1", "hold"],
    ] {
        let output = std::process::Command::new(bin("cell"))
            .args(command)
            .args([
                "--cell",
                "t-tls",
                "--connect",
                "tls/127.0.0.1:9",
                "--timeout-ms",
                "500",
            ])
            .output()
            .unwrap();
        assert!(!output.status.success());
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(
            stderr.contains("give --pki DIR"),
            "cell {command:?}: {stderr}"
        );
    }
}
