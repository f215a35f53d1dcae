//! `cell dashboard` against a real cell: the page and its live updates, the JSON API,
//! alarms (raised when a robot's process is killed, acknowledged by an operator),
//! `/metrics`, and a read-only dashboard refusing what only operators may do.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use holarchy_tests::webdriver;
use holarchy_tests::*;
use schemas::HolonId;

/// A `cell dashboard` process and its web server.
struct Dashboard {
    child: Child,
    api: Api,
}

/// A dashboard's web server, by its address.
struct Api {
    address: String,
}

impl std::ops::Deref for Dashboard {
    type Target = Api;
    fn deref(&self) -> &Api {
        &self.api
    }
}

impl Dashboard {
    fn start(cell: &Cell, extra: &[&str]) -> Dashboard {
        Dashboard::start_on(cell.keys.cell(), &cell.endpoint, extra)
    }

    /// A dashboard of cell `cell` through the router at `endpoint`.
    fn start_on(cell: &str, endpoint: &str, extra: &[&str]) -> Dashboard {
        let mut child = Command::new(bin("cell"))
            .args(["dashboard", "--cell", cell, "--connect", endpoint])
            .args(["--listen", "127.0.0.1:0"])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        // "dashboard of cell C on http://127.0.0.1:PORT/"
        let address = line
            .trim()
            .rsplit("http://")
            .next()
            .unwrap()
            .trim_end_matches('/')
            .to_string();
        assert!(address.starts_with("127.0.0.1:"), "{line}");
        Dashboard {
            child,
            api: Api { address },
        }
    }
}

impl Api {
    /// One HTTP/1.1 request as the dashboard's own page makes it (its host, and for a
    /// change its own `Origin` and JSON): the status code and the body.
    fn http(&self, method: &str, path: &str, body: &str) -> (u16, String) {
        let origin = format!("http://{}", self.address);
        let mut headers = vec![("content-type", "application/json")];
        if method != "GET" {
            headers.push(("origin", origin.as_str()));
        }
        let (status, _, body) = self.raw(method, path, &self.address, &headers, body);
        (status, body)
    }

    /// One HTTP/1.1 request with `host` and `headers` as given: the status code, the
    /// response's headers and its body.
    fn raw(
        &self,
        method: &str,
        path: &str,
        host: &str,
        headers: &[(&str, &str)],
        body: &str,
    ) -> (u16, String, String) {
        let mut stream = TcpStream::connect(&self.address).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let mut request =
            format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
        for (name, value) in headers {
            request.push_str(&format!("{name}: {value}\r\n"));
        }
        request.push_str(&format!("content-length: {}\r\n\r\n{body}", body.len()));
        stream.write_all(request.as_bytes()).unwrap();
        let mut response = String::new();
        stream.read_to_string(&mut response).unwrap();
        let status = response
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        let (head, body) = response
            .split_once("\r\n\r\n")
            .map(|(h, b)| (h.to_string(), b.to_string()))
            .unwrap_or_default();
        (status, head, body)
    }

    fn json(&self, path: &str) -> serde_json::Value {
        let (status, body) = self.http("GET", path, "");
        assert_eq!(status, 200, "{path}: {body}");
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("{path}: {e}: {body}"))
    }

    /// Waits until `check` holds on `GET path` (a JSON answer).
    fn wait(&self, path: &str, what: &str, check: impl Fn(&serde_json::Value) -> bool) -> Duration {
        let started = Instant::now();
        loop {
            let value = self.json(path);
            if check(&value) {
                return started.elapsed();
            }
            assert!(
                started.elapsed() < WAIT,
                "{what} never showed on {path}: {value}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Dashboard {
    fn drop(&mut self) {
        if let Err(e) = self.child.kill() {
            eprintln!("cannot stop the dashboard: {e}");
        }
        if let Err(e) = self.child.wait() {
            eprintln!("cannot reap the dashboard: {e}");
        }
    }
}

/// Submits `count` work orders of `product` with the page's form: the new orders'
/// names, as the page reports them (waits up to `within` for its answer).
fn submit_from_page(
    browser: &webdriver::Browser,
    product: &str,
    count: u32,
    within: Duration,
) -> Vec<String> {
    let field = browser.find("#product").unwrap().unwrap();
    browser.type_into(&field, product).unwrap();
    let field = browser.find("#count").unwrap().unwrap();
    browser.type_into(&field, &count.to_string()).unwrap();
    let submit = browser.find("#submit button").unwrap().unwrap();
    browser.click(&submit).unwrap();
    let (answer, _) = browser.wait_for("#submitted", within).unwrap();
    let deadline = Instant::now() + within;
    let text = loop {
        let text = browser.text(&answer).unwrap();
        if !text.is_empty() || Instant::now() >= deadline {
            break text;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(text.starts_with("submitted orders1-"), "{text}");
    text.trim_start_matches("submitted ")
        .split(", ")
        .map(String::from)
        .collect()
}

/// Filters the page's orders to `done` and waits until each of `orders` is listed so.
fn wait_done_on_page(browser: &webdriver::Browser, orders: &[String], within: Duration) {
    let done_filter = browser
        .find("#status-filter option:nth-child(3)")
        .unwrap()
        .unwrap();
    browser.click(&done_filter).unwrap();
    for order in orders {
        browser
            .wait_for(
                &format!("tr[data-order=\"{order}\"][data-status=\"done\"]"),
                within,
            )
            .unwrap();
    }
}

/// Reads the server-sent events of `/events` until a `view` event comes: its data.
fn first_view(address: &str) -> serde_json::Value {
    let mut stream = TcpStream::connect(address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    write!(
        stream,
        "GET /events HTTP/1.1\r\nHost: {address}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    let mut in_view = false;
    loop {
        line.clear();
        assert!(
            reader.read_line(&mut line).unwrap() > 0,
            "the event stream ended"
        );
        let text = line.trim_end();
        if text == "event: view" {
            in_view = true;
        } else if let (true, Some(data)) = (in_view, text.strip_prefix("data: ")) {
            return serde_json::from_str(data).unwrap();
        }
    }
}

fn live(value: &serde_json::Value, holon: &str) -> Option<bool> {
    value
        .as_array()?
        .iter()
        .find(|h| h["holon"] == holon)
        .map(|h| h["live"] == true)
}

#[tokio::test(flavor = "multi_thread")]
async fn the_dashboard_shows_the_cell_raises_alarms_and_serves_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-dashboard").await.unwrap();
    let mut robot = cell.resource(dir.path(), "robot1").start().await.unwrap();

    let observer = Dashboard::start(&cell, &[]);
    let operator = Dashboard::start(&cell, &["--operator"]);
    // The page, its live view, and the API all know the robot.
    let (status, page) = observer.http("GET", "/", "");
    assert_eq!(status, 200);
    assert!(
        page.contains("<title>holarchy cell</title>")
            && page.contains("new EventSource(\"/events\")")
    );
    observer.wait("/api/holons", "robot1, free", |h| {
        h.as_array().is_some_and(|a| {
            a.iter()
                .any(|h| h["holon"] == "resource/robot1" && h["resource"]["state"] == "free")
        })
    });
    let view = first_view(&observer.address);
    assert_eq!(view["cell"], "t-dashboard");
    assert!(
        view["holons"].to_string().contains("resource/robot1"),
        "{view}"
    );
    assert_eq!(view["operator"], false);

    // Killed: the robot shows gone, with an alarm.
    robot.node.kill();
    let shown = observer.wait("/api/holons", "robot1 gone", |h| {
        live(h, "resource/robot1") == Some(false)
    });
    println!("robot1 shown gone {shown:?} after its kill");
    let alarms = observer.json("/api/alarms");
    let alarm = alarms
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["kind"] == "vanished" && a["source"] == "resource/robot1")
        .unwrap_or_else(|| panic!("no alarm: {alarms}"))
        .clone();
    assert!(alarm.get("cleared").is_none(), "{alarm}");
    let events = observer.json("/api/events");
    assert!(events.to_string().contains("vanished"), "{events}");

    // A read-only dashboard refuses to acknowledge or submit.
    let id = alarm["id"].as_u64().unwrap();
    let (status, body) = observer.http("POST", &format!("/api/alarms/{id}/ack"), "");
    assert_eq!(status, 403, "{body}");
    let (status, body) = observer.http("POST", "/api/orders", r#"{"product":"breaker","count":1}"#);
    assert_eq!(status, 403, "{body}");
    let (status, body) = observer.http(
        "POST",
        "/api/resources/robot1/packml",
        r#"{"command":"hold"}"#,
    );
    assert_eq!(status, 403, "an observer's page holds no robot: {body}");

    // Metrics in the Prometheus text format.
    let (status, metrics) = observer.http("GET", "/metrics", "");
    assert_eq!(status, 200);
    assert!(
        metrics.contains("# TYPE holarchy_holons gauge"),
        "{metrics}"
    );
    assert!(metrics.contains("holarchy_alarms_active 1"), "{metrics}");
    assert!(
        metrics.contains("# TYPE holarchy_delivery_retries_total counter"),
        "{metrics}"
    );

    // An operator's dashboard acknowledges; back, the alarm clears and leaves the list.
    operator.wait("/api/alarms", "the alarm", |a| {
        a.as_array().is_some_and(|a| !a.is_empty())
    });
    let alarms = operator.json("/api/alarms");
    let id = alarms[0]["id"].as_u64().unwrap();
    let (status, body) = operator.http("POST", &format!("/api/alarms/{id}/ack"), "");
    assert_eq!(status, 204, "{body}");
    operator.wait("/api/alarms", "acknowledged", |a| {
        a[0]["acknowledged"].is_u64()
    });
    robot.node = start_node(
        dir.path(),
        &robot.config,
        cell.keys.cell(),
        &cell.endpoint,
        &robot.sim.address,
        &[],
    )
    .unwrap();
    operator.wait("/api/alarms", "the alarm cleared and gone", |a| {
        a.as_array().is_some_and(|a| a.is_empty())
    });
    operator.wait("/api/holons", "robot1 back", |h| {
        live(h, "resource/robot1") == Some(true)
    });
    // The robot's snapshot names its machine.
    let holons = operator.json("/api/holons");
    assert!(
        holons
            .to_string()
            .contains(&format!("\"host\":\"{}\"", holon::presence::host_name())),
        "{holons}"
    );

    // An order-node shows in the network panel; killed, it raises `vanished`.
    let mut node = cell.start_order_node(dir.path(), &[]).await.unwrap();
    let process = |v: &serde_json::Value| {
        v["processes"]
            .as_array()
            .and_then(|p| p.iter().find(|p| p["process"] == "order-node/orders1"))
            .map(|p| p["live"] == true)
    };
    operator.wait("/api/view", "order-node/orders1 live", |v| {
        process(v) == Some(true)
    });
    node.kill();
    operator.wait("/api/view", "order-node/orders1 gone", |v| {
        process(v) == Some(false)
    });
    operator.wait("/api/alarms", "order-node/orders1 vanished", |a| {
        a.as_array().is_some_and(|a| {
            a.iter()
                .any(|a| a["kind"] == "vanished" && a["source"] == "order-node/orders1")
        })
    });
    // Zenoh tells the dashboard which router its session is linked to.
    let view = operator.json("/api/view");
    assert_eq!(
        view["linked_routers"].as_array().map(Vec::len),
        Some(1),
        "{view}"
    );
}

/// In a real browser (headless Chromium): the page lists the cell's holons; a robot
/// killed shows gone with an alarm without a reload; work orders submitted from the
/// page are done. A screenshot of the page is left in `target/dashboard.png`.
#[tokio::test(flavor = "multi_thread")]
async fn in_a_browser_the_page_follows_the_cell_and_submits_work() {
    if let Err(why) = webdriver::browser_available() {
        println!("SKIPPED: the browser test needs Chromium ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-dashboard-page").await.unwrap();
    // The breaker's cell: a conveyor, a robot, an inspection station (each with its
    // controller), the product and an order-node.
    let mut sims = Vec::new();
    let mut holons = Vec::new();
    for (name, config) in [
        ("conveyor1", "conveyor1.toml"),
        ("robot1", "robot1.toml"),
        ("inspect1", "inspect1.toml"),
    ] {
        let sim = Sim::start(
            dir.path(),
            &format!("{name}-sim"),
            "127.0.0.1:0",
            &["--delay-ms", "50"],
        )
        .unwrap();
        let process = start_holon(
            dir.path(),
            "holon-node",
            &demo_config(config),
            name,
            &cell,
            &["--controller", &sim.address],
        )
        .unwrap();
        cell.wait_alive(&HolonId::resource(name).unwrap())
            .await
            .unwrap();
        sims.push(sim);
        holons.push(process);
    }
    let breaker = start_holon(
        dir.path(),
        "holon-node",
        &stationary_breaker(),
        "breaker",
        &cell,
        &[],
    )
    .unwrap();
    let orders = cell.start_order_node(dir.path(), &[]).await.unwrap();
    let dashboard = Dashboard::start(&cell, &["--operator"]);

    let browser = webdriver::Browser::start(&dir.path().join("profile")).unwrap();
    browser
        .goto(&format!("http://{}/", dashboard.address))
        .unwrap();
    let within = Duration::from_secs(10);
    for holon in [
        "resource/robot1",
        "resource/conveyor1",
        "resource/inspect1",
        "product/breaker",
    ] {
        browser
            .wait_for(&format!("tr[data-holon=\"{holon}\"]"), within)
            .unwrap();
    }

    // The layout the resources state (docs/material-flow.md): the conveyor's loop, a
    // box per location at its stopper, the stoppers nobody docks at drawn free.
    for location in ["conveyor1.load", "robot1.port", "inspect1.port"] {
        browser
            .wait_for(&format!("#layout [data-location=\"{location}\"]"), within)
            .unwrap();
    }
    browser
        .wait_for(
            "#layout [data-stopper=\"conveyor1.s2\"][data-free=\"true\"]",
            within,
        )
        .unwrap();
    browser
        .wait_for(
            "#layout [data-stopper=\"conveyor1.s1\"][data-free=\"false\"]",
            within,
        )
        .unwrap();

    // Killed: gone, with an active alarm, without a reload.
    holons[1].kill();
    let (alarm, took) = browser
        .wait_for(
            "tr.alarm-row.active[data-source=\"resource/robot1\"]",
            within,
        )
        .unwrap();
    println!("the page showed the alarm {took:?} after the kill");
    assert!(browser.text(&alarm).unwrap().contains("vanished"));
    browser
        .wait_for("tr.gone[data-holon=\"resource/robot1\"]", within)
        .unwrap();
    // Its part of the layout left with it: its stopper is free.
    browser
        .wait_for(
            "#layout [data-stopper=\"conveyor1.s1\"][data-free=\"true\"]",
            within,
        )
        .unwrap();

    // The robot back, two breakers ordered from the page: both done.
    holons[1] = start_holon(
        dir.path(),
        "holon-node",
        &demo_config("robot1.toml"),
        "robot1",
        &cell,
        &["--controller", &sims[1].address],
    )
    .unwrap();
    browser
        .wait_for("tr[data-holon=\"resource/robot1\"]:not(.gone)", within)
        .unwrap();
    browser
        .wait_for(
            "#layout [data-stopper=\"conveyor1.s1\"][data-free=\"false\"]",
            within,
        )
        .unwrap();
    let orders_submitted = submit_from_page(&browser, "breaker", 2, within);
    assert_eq!(orders_submitted.len(), 2, "{orders_submitted:?}");
    wait_done_on_page(&browser, &orders_submitted, Duration::from_secs(60));
    // The running schedule: each order's jobs drawn on the robot's and the conveyor's
    // rows, ended (none running), and nothing waiting.
    for order in &orders_submitted {
        for (resource, service) in [("robot1", "pick_n_place"), ("conveyor1", "transport")] {
            let bar = format!(
                "#schedule .gantt-row[data-resource=\"{resource}\"] rect.job[data-job-order=\"{order}\"][data-service=\"{service}\"]:not(.running)"
            );
            browser.wait_for(&bar, within).unwrap();
        }
    }
    browser
        .wait_for(
            "#schedule .gantt-row[data-resource=\"robot1\"] [data-waiting=\"0\"]",
            within,
        )
        .unwrap();
    // The history panel reads the finished orders from the order-node's journal.
    browser
        .execute("document.getElementById('history-box').open = true")
        .unwrap();
    browser.wait_for("#history-node option", within).unwrap();
    let (newest, _) = browser.wait_for("#history-first", within).unwrap();
    browser.click(&newest).unwrap();
    for order in &orders_submitted {
        browser
            .wait_for(&format!("#history tr[data-order=\"{order}\"]"), within)
            .unwrap();
    }
    let (answer, _) = browser.wait_for("#history-answer", within).unwrap();
    assert!(
        browser
            .text(&answer)
            .unwrap()
            .contains("orders1: 2 finished"),
        "{}",
        browser.text(&answer).unwrap()
    );
    // The steps were timed: two transports on the conveyor.
    let (_, metrics) = dashboard.http("GET", "/metrics", "");
    assert!(
        metrics.contains(
            "holarchy_step_duration_seconds_count{service_type=\"transport\",resource=\"conveyor1\"} 2"
        ),
        "{metrics}"
    );
    // PackML from the page: Hold robot1 (it is idle: Held at once), the page then offers
    // Unhold instead of Hold; Unhold brings it back to Execute.
    let (hold, _) = browser
        .wait_for(
            "button[data-packml=\"hold\"][data-resource=\"robot1\"]",
            within,
        )
        .unwrap();
    browser.click(&hold).unwrap();
    cell.wait_packml("robot1", 11).await.unwrap();
    let (unhold, _) = browser
        .wait_for(
            "button[data-packml=\"unhold\"][data-resource=\"robot1\"]",
            within,
        )
        .unwrap_or_else(|e| {
            // What the dashboard and the page held then (a run once failed here).
            let (_, holons) = dashboard.http("GET", "/api/holons", "");
            let row = browser
                .find("tr[data-holon=\"resource/robot1\"]")
                .ok()
                .flatten()
                .and_then(|row| browser.text(&row).ok());
            panic!("the page never offered Unhold: {e}; the page's robot1 row: {row:?}; the dashboard's holons: {holons}")
        });
    let row = browser
        .find("tr[data-holon=\"resource/robot1\"] .packml-state")
        .unwrap()
        .expect("robot1's PackML cell");
    assert_eq!(browser.text(&row).unwrap(), "Held (11)");
    let screenshot = workspace_root().join("target").join("dashboard.png");
    browser.screenshot(&screenshot).unwrap();
    println!("screenshot: {}", screenshot.display());
    browser.click(&unhold).unwrap();
    cell.wait_packml("robot1", 6).await.unwrap();
    browser
        .wait_for(
            "button[data-packml=\"hold\"][data-resource=\"robot1\"]",
            within,
        )
        .unwrap();
    drop((breaker, orders));
}

/// Another web page, opened in an operator's browser, cannot act through the dashboard:
/// a DNS-rebound page (its own host name) is refused outright, and a cross-site form or
/// script cannot change anything (no same-origin `Origin`, or not JSON); the dashboard's
/// own page and tools that say where they come from work, and every answer keeps out of
/// other sites' frames.
#[tokio::test(flavor = "multi_thread")]
async fn another_site_cannot_act_through_the_dashboard() {
    let cell = Cell::open("t-dashboard-sites").await.unwrap();
    let operator = Dashboard::start(&cell, &["--operator"]);
    let port = operator.address.rsplit_once(':').unwrap().1.to_string();
    let evil_host = format!("evil.example:{port}");
    let work = r#"{"product":"breaker","count":1}"#;
    // DNS rebinding: the attacker's name in Host. Neither a read nor a change.
    let json = [("content-type", "application/json")];
    let (status, _, body) = operator.raw("GET", "/api/orders", &evil_host, &[], "");
    assert_eq!(status, 421, "{body}");
    let rebound = [
        ("content-type", "application/json"),
        ("origin", "http://evil.example"),
    ];
    let (status, _, body) = operator.raw("POST", "/api/orders", &evil_host, &rebound, work);
    assert_eq!(status, 421, "{body}");
    // A cross-site form post to acknowledge an alarm, and a cross-site JSON submit.
    let form = [
        ("content-type", "application/x-www-form-urlencoded"),
        ("origin", "http://evil.example"),
    ];
    let (status, _, body) = operator.raw("POST", "/api/alarms/1/ack", &operator.address, &form, "");
    assert_eq!(status, 403, "{body}");
    let (status, _, body) = operator.raw("POST", "/api/orders", &operator.address, &rebound, work);
    assert_eq!(status, 403, "{body}");
    // A change without Origin, or not JSON, from the right host: refused too.
    let (status, _, body) = operator.raw("POST", "/api/orders", &operator.address, &json, work);
    assert_eq!(status, 403, "{body}");
    let own = format!("http://{}", operator.address);
    let not_json = [("content-type", "text/plain"), ("origin", own.as_str())];
    let (status, _, body) = operator.raw("POST", "/api/orders", &operator.address, &not_json, work);
    assert_eq!(status, 415, "{body}");
    // Nothing was submitted: no order-node ever saw a work order.
    assert_eq!(
        operator.json("/api/orders").as_array().map(Vec::len),
        Some(0)
    );
    // Its own names work; every answer carries the frame and sniffing headers.
    let (status, head, _) = operator.raw("GET", "/api/view", &format!("localhost:{port}"), &[], "");
    assert_eq!(status, 200);
    let head = head.to_ascii_lowercase();
    for header in [
        "x-frame-options: deny",
        "content-security-policy: frame-ancestors 'none'",
        "x-content-type-options: nosniff",
    ] {
        assert!(head.contains(header), "{header} missing: {head}");
    }
    // A name of the plant's DNS, given with --host-name, is one of its own.
    let named = Dashboard::start(&cell, &["--host-name", "Dashboard.Plant"]);
    let port = named.address.rsplit_once(':').unwrap().1.to_string();
    let (status, _, _) = named.raw(
        "GET",
        "/api/view",
        &format!("dashboard.plant:{port}"),
        &[],
        "",
    );
    assert_eq!(status, 200);
    let (status, _, _) = named.raw("GET", "/api/view", &format!("other.plant:{port}"), &[], "");
    assert_eq!(status, 421);
}

/// `cell demo --dashboard --keep`: the demo's dashboard shows its orders done, the cell
/// stays up after the summary, and Ctrl-C (SIGTERM) stops it all with exit 0.
#[test]
fn the_demo_keeps_its_cell_up_with_a_dashboard() {
    let mut demo = Command::new(bin("cell"))
        .args(["demo", "--orders", "2", "--delay-ms", "30", "--no-hot-add"])
        .args(["--inspect-fail-every", "0", "--cell", "t-demo-keep"])
        .args(["--dashboard", "--listen", "127.0.0.1:0", "--keep"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(demo.stdout.take().unwrap()).lines();
    let mut seen = Vec::new();
    let mut address = None;
    let deadline = Instant::now() + Duration::from_secs(120);
    while Instant::now() < deadline {
        let Some(Ok(line)) = lines.next() else { break };
        seen.push(line.clone());
        if let Some(url) = line.split("on http://").nth(1) {
            address = Some(url.trim_end_matches('/').to_string());
        }
        if line.starts_with("the cell stays up (--keep)") {
            break;
        }
    }
    let address = address.unwrap_or_else(|| panic!("no dashboard address: {seen:#?}"));
    assert!(
        seen.iter().any(|l| l.starts_with("the cell stays up")),
        "{seen:#?}"
    );
    let dashboard = Api { address };
    dashboard.wait("/api/orders", "both orders done", |o| {
        o.as_array()
            .is_some_and(|o| o.len() == 2 && o.iter().all(|o| o["status"] == "done"))
    });
    // The demo moves its parts: each order's part left by the loading point, and the
    // page has where it is to draw.
    let orders = dashboard.json("/api/orders");
    for order in orders.as_array().unwrap() {
        assert_eq!(order["part"]["state"], "shipped", "{order:#}");
        assert_eq!(order["part"]["exit"], "conveyor1.load", "{order:#}");
    }
    // The demo's router announces itself by this machine's name, its order-node too.
    let router = format!("router/{}", holon::presence::host_name());
    dashboard.wait("/api/view", "the router and the order-node", |v| {
        let live = |name: &str| {
            v["processes"]
                .as_array()
                .is_some_and(|p| p.iter().any(|p| p["process"] == name && p["live"] == true))
        };
        live(&router) && live("order-node/orders1")
    });
    // The totals are the node's counts; older finished orders come a page at a time
    // from the node's journal, newest first.
    dashboard.wait("/api/view", "the node's counts", |v| {
        v["order_counts"]["done"] == 2 && v["order_counts"]["running"] == 0
    });
    let page = dashboard.json("/api/orders/history?node=orders1&status=done&limit=1");
    assert_eq!(page["orders"].as_array().map(Vec::len), Some(1), "{page}");
    assert_eq!(page["orders"][0]["holon"], "order/orders1-2", "{page}");
    assert_eq!(page["counts"]["done"], 2, "{page}");
    assert_eq!(page["next"]["after_finished"], 2, "{page}");
    let older = dashboard.json("/api/orders/history?node=orders1&status=done&before=2");
    assert_eq!(older["orders"][0]["holon"], "order/orders1-1", "{older}");
    assert!(older.get("next").is_none(), "the last page: {older}");
    let (status, refused) = dashboard.http("GET", "/api/orders/history?node=orders1&page=2", "");
    assert_eq!(status, 400, "{refused}");
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(demo.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = demo.wait().unwrap();
    assert!(status.success(), "{rest:#?}");
    assert!(
        rest.iter()
            .any(|l| l.contains("stopping everything the demo started")),
        "{rest:#?}"
    );
}

/// A resource's state publication lost on its way (zenoh drops a sample when a link's
/// queue stays full a moment) is not shown stale for good: the dashboard asks every
/// resource's state again every few seconds. The test stands in for a resource whose
/// change is never published: its token and its state's queryable, answering a new
/// state that no publication announces.
#[tokio::test(flavor = "multi_thread")]
async fn a_resource_state_whose_publication_was_lost_is_shown_all_the_same() {
    use std::sync::{Arc, Mutex};
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-lost").await.unwrap();
    // A real resource's state, as the stand-in's first answer.
    let mut robot = cell.resource(dir.path(), "robot1").start().await.unwrap();
    let mut state = cell.wait_packml("robot1", 6).await.unwrap();
    robot.node.kill();
    cell.wait_gone(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    let robot9 = HolonId::resource("robot9").unwrap();
    state["holon"] = serde_json::json!(robot9.to_string());
    state["at"] = serde_json::json!(schemas::unix_ms());
    let answered = Arc::new(Mutex::new(state.clone()));
    let _queryable = cell
        .session
        .declare_queryable(cell.keys.state(&robot9))
        .callback({
            let (answered, key) = (answered.clone(), cell.keys.state(&robot9));
            move |query| {
                use zenoh::Wait;
                let state = answered.lock().unwrap().clone();
                if let Err(e) = query
                    .reply(key.clone(), serde_json::to_vec(&state).unwrap())
                    .wait()
                {
                    eprintln!("the stand-in cannot answer its state: {e}");
                }
            }
        })
        .await
        .unwrap();
    let _token = cell
        .session
        .liveliness()
        .declare_token(cell.keys.alive(&robot9))
        .await
        .unwrap();
    let dashboard = Dashboard::start(&cell, &[]);
    let packml = |holons: &serde_json::Value| -> Option<i64> {
        holons
            .as_array()?
            .iter()
            .find(|h| h["holon"] == "resource/robot9")?["resource"]["packml"]["state_number"]
            .as_i64()
    };
    dashboard.wait("/api/holons", "robot9 in Execute", |h| packml(h) == Some(6));
    // Past the asks that follow a newcomer's token: the new state is only answered.
    std::thread::sleep(Duration::from_millis(1500));
    state["packml"]["state"] = serde_json::json!("held");
    state["packml"]["state_number"] = serde_json::json!(11);
    state["at"] = serde_json::json!(schemas::unix_ms());
    *answered.lock().unwrap() = state;
    dashboard.wait("/api/holons", "robot9 Held, never published", |h| {
        packml(h) == Some(11)
    });
}
