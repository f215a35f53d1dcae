use super::*;

const DEMO: &str = include_str!("../../../deploy/cells/demo/robot1.toml");

#[test]
fn the_demo_config_loads() {
    let config = ResourceConfig::parse(DEMO, "robot1.toml", Overrides::default()).unwrap();
    assert_eq!(config.holon.to_string(), "resource/robot1");
    assert_eq!(config.keys.cell(), "demo");
    let pnp = config.catalog.get("pick_n_place").unwrap();
    assert_eq!(pnp.steps.len(), 2);
    assert_eq!(pnp.steps[0].action, "pick");
    assert_eq!(pnp.steps[0].until, vec!["picking_done".to_string()]);
    assert!(!config.zenoh.multicast_scouting);
}

#[test]
fn a_scaled_plant_counts_the_configs_plant_times_in_wall_time() {
    const CONVEYOR: &str = include_str!("../../../deploy/cells/demo/conveyor1.toml");
    let travel = |config: &ResourceConfig| {
        let Some(schemas::layout::TransporterSpec::Conveyor(c)) =
            &config.layout.as_ref().unwrap().transporter
        else {
            panic!("conveyor1 is a conveyor");
        };
        (c.travel_ms("load", "s1").unwrap(), c.dock_ms)
    };
    let nominal = |config: &ResourceConfig| {
        config
            .catalog
            .get("transport")
            .unwrap()
            .nominal_duration
            .as_millis() as u64
    };
    let real = ResourceConfig::parse(CONVEYOR, "conveyor1.toml", Overrides::default()).unwrap();
    let scaled = ResourceConfig::parse(
        CONVEYOR,
        "conveyor1.toml",
        Overrides {
            time_scale: "20".parse().unwrap(),
            ..Overrides::default()
        },
    )
    .unwrap();
    assert_eq!(nominal(&scaled), nominal(&real) / 20);
    let ((real_travel, real_dock), (travel_20, dock_20)) = (travel(&real), travel(&scaled));
    assert!(real_travel > 0);
    assert!(real_travel / 20 - 1 <= travel_20 && travel_20 <= real_travel / 20 + 1);
    assert_eq!(dock_20, (real_dock as f64 / 20.0).round() as u64);
    assert_eq!(scaled.time_scale.factor(), 20.0);
}

#[test]
fn the_command_line_overrides_the_file() {
    let overrides = Overrides {
        common: holon::session::CommandLine {
            cell: Some("line2".into()),
            name: Some("robot7".into()),
            connect: vec!["tcp/127.0.0.1:9000".into()],
            ..Default::default()
        },
        controller: Some("127.0.0.1:9100".into()),
        ..Overrides::default()
    };
    let config = ResourceConfig::parse(DEMO, "robot1.toml", overrides).unwrap();
    assert_eq!(config.holon.to_string(), "resource/robot7");
    assert_eq!(config.keys.cell(), "line2");
    assert_eq!(config.zenoh.connect, vec!["tcp/127.0.0.1:9000".to_string()]);
    assert_eq!(config.controller.address, "127.0.0.1:9100");
}

#[test]
fn bad_configs_say_what_is_wrong() {
    let cases = [
        ("name = \"robot1\"", "name = \"Robot 1\"", "name"),
        ("cell = \"demo\"", "cell = \"\"", "cell"),
        (
            "strategy = \"one_for_one\"",
            "strategy = \"one_for_some\"",
            "strategy",
        ),
        ("capacity = 64", "capacity = 0", "agenda.capacity"),
        (
            "address = \"127.0.0.1:7601\"",
            "address = \"127.0.0.1:7601\"\njobs_at_once = 0",
            "controller.jobs_at_once must be at least 1",
        ),
        (
            "dialect = \"holarchy-xml\"",
            "dialect = \"kuka-eki\"\njobs_at_once = 2",
            "controller.jobs_at_once = 2: the dialect kuka-eki has one request in flight",
        ),
        (
            "command_timeout_ms = 30000",
            "command_timeout_ms = 0",
            "command_timeout_ms",
        ),
        ("until = [\"picking_done\"]", "until = []", "until"),
        ("until = [\"picking_done\"]", "until = [\"error\"]", "error"),
            ("action = \"pick\"", "action = \"\"", "action"),
        ("[agenda]", "[agenda]\ncolour = \"red\"", "colour"),
            (
                "address = \"127.0.0.1:7601\"",
            "address = \"nowhere\"",
            "controller.address",
        ),
        (
            "address = \"127.0.0.1:7601\"",
            "address = \"127.0.0.1:99999\"",
            "port must be a number from 1 to 65535",
        ),
        (
            "address = \"127.0.0.1:7601\"",
            "address = \":7601\"",
            "is not HOST:PORT",
        ),
        (
            "requester_grace_ms = 60000",
            "requester_grace_ms = 10",
            "agenda.requester_grace_ms",
        ),
        (
            "reconnect_max_ms = 10000",
            "reconnect_max_ms = 500",
            "controller.reconnect_max_ms (500) must be at least controller.reconnect_interval_ms (1000)",
        ),
        (
            "reconnect_max_ms = 10000",
            "reconnect_max_ms = 0",
            "controller.reconnect_max_ms must be greater than 0",
        ),
    ];
    for (from, to, expect) in cases {
        assert!(DEMO.contains(from), "the demo config lacks {from:?}");
        let text = DEMO.replacen(from, to, 1);
        let err = ResourceConfig::parse(&text, "robot1.toml", Overrides::default())
            .expect_err(to)
            .to_string();
        assert!(err.contains(expect), "{to}: {err}");
    }
    let err = ResourceConfig::load(Path::new("/nonexistent.toml"), Overrides::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("/nonexistent.toml"), "{err}");
}
